"""Atomic writes of files: a temporary file next to the target, published when complete.

:func:`atomic_write` is the one way cellcoadd writes a file (patch coadds, exposures,
simulation descriptions and tables, command-line outputs).
Readers see either the previous file or the complete new one, never a partial file. A
process killed mid-write can leave a hidden temporary file (``.<name>.tmp-<random>``)
behind; it is safe to delete.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Callable
from pathlib import Path

from cellcoadd.io.disk_space import disk_full_error


def exists_error(target: str | os.PathLike[str]) -> FileExistsError:
    """The error of a write that would replace ``target`` without ``overwrite``."""
    return FileExistsError(f"{os.fspath(target)} exists; pass overwrite=True to replace it")


def atomic_write(
    target: str | os.PathLike[str],
    write: Callable[[Path], None],
    *,
    overwrite: bool = False,
    prepare: Callable[[Path], None] | None = None,
    on_failure: Callable[[], None] | None = None,
) -> Path:
    """Write ``target`` atomically: ``write(temporary)``, flush to disk, then publish.

    The temporary file is in the target's directory. It is published by a hard link when
    ``overwrite`` is false, which fails if the target appeared meanwhile (so of two
    concurrent writers of a new file exactly one succeeds and an existing file is never
    replaced), and by ``os.replace`` otherwise. On any failure the temporary file is
    removed and a previous file at ``target`` is left unchanged.

    Parameters
    ----------
    target : path-like
        The file to write.
    write : callable
        ``write(temporary)`` creates the file at the path it is given (which does not
        exist yet) and writes all of it.
    overwrite : bool
        Replace an existing ``target`` (FileExistsError otherwise).
    prepare : callable, optional
        ``prepare(temporary)`` runs before anything is written (checks that should refuse
        the write up front); its exceptions pass through unchanged.
    on_failure : callable, optional
        Called after a failed write, once the temporary file is removed.

    Returns
    -------
    Path
        ``target``.

    Raises
    ------
    FileExistsError
        ``target`` exists (or appears during the write) and ``overwrite`` is false.
    FileNotFoundError
        The target's directory does not exist.
    OSError
        ``errno.ENOSPC`` when the failure came from a full disk
        (:func:`~cellcoadd.io.disk_space.disk_full_error`).
    """
    target = Path(os.fspath(target))
    if target.exists() and not overwrite:
        raise exists_error(target)
    directory = target.parent
    if not directory.is_dir():
        raise FileNotFoundError(f"{directory}: no such directory")
    temporary = directory / f".{target.name}.tmp-{secrets.token_hex(8)}"
    if prepare is not None:
        prepare(temporary)
    try:
        write(temporary)
        _fsync_file(temporary)
        _publish(temporary, target, overwrite=overwrite)
    except BaseException as err:
        full = disk_full_error(target, err) if isinstance(err, Exception) else None
        temporary.unlink(missing_ok=True)
        if on_failure is not None:
            on_failure()
        if full is not None:
            raise full from err
        raise
    _fsync_directory(directory)
    return target


def atomic_write_text(
    target: str | os.PathLike[str], text: str, *, overwrite: bool = False
) -> Path:
    """:func:`atomic_write` of ``text`` into ``target``, encoded as by ``Path.write_text``."""

    def write(temporary: Path) -> None:
        temporary.write_text(text)

    return atomic_write(target, write, overwrite=overwrite)


def _publish(temporary: Path, target: Path, *, overwrite: bool) -> None:
    if overwrite:
        os.replace(temporary, target)
        return
    # A hard link fails if the target appeared meanwhile, so nothing is clobbered.
    try:
        os.link(temporary, target)
    except FileExistsError:
        raise exists_error(target) from None
    except OSError:
        if target.exists():
            raise exists_error(target) from None
        os.replace(temporary, target)  # file systems without hard links
        return
    temporary.unlink()


def _fsync_file(path: Path) -> None:
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def _fsync_directory(directory: Path) -> None:
    # Makes the rename durable; not every platform can open a directory.
    try:
        descriptor = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)
