"""Atomic writes of files: a temporary file next to the target, published when complete.

:func:`atomic_write` is the one way cellcoadd writes a file (patch coadds, exposures,
simulation descriptions and tables, command-line outputs).
Readers see either the previous file or the complete new one, never a partial file.

Temporary files are named ``.<name>.tmp-<host>-<pid>-<random>`` (:func:`temporary_name`):
the target's name, the host and the process writing it. A process killed mid-write leaves
its temporary file behind; the next write of the same target on the same host removes
every such file whose process no longer runs (:func:`remove_stale_temporaries`), so
repeated crashes do not pile up partial files. Temporary files of other hosts, of live
processes, and of other targets are left alone; they are safe to delete by hand.
"""

from __future__ import annotations

import os
import re
import secrets
import socket
from collections.abc import Callable
from pathlib import Path

from cellcoadd.errors import CellCoaddFileExistsError, CellCoaddFileNotFoundError
from cellcoadd.io._files.disk_space import disk_full_error
from cellcoadd.io._files.path_gate import gate_write
from cellcoadd.io._files.writeback import EarlyWriteback


def exists_error(target: str | os.PathLike[str]) -> FileExistsError:
    """The error of a write that would replace ``target`` without ``overwrite``."""
    return CellCoaddFileExistsError(
        f"{os.fspath(target)} exists; pass overwrite=True to replace it", path=target
    )


def _host_tag() -> str:
    # the host, as a name part CFITSIO and shells read literally
    return re.sub(r"[^A-Za-z0-9]", "", socket.gethostname())[:32] or "host"


def temporary_name(target: str | os.PathLike[str]) -> str:
    """Name of a new temporary file for ``target``: ``.<name>.tmp-<host>-<pid>-<random>``."""
    name = Path(os.fspath(target)).name
    return f".{name}.tmp-{_host_tag()}-{os.getpid()}-{secrets.token_hex(8)}"


def _process_is_gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # exists, owned by someone else
        return False
    return False


def remove_stale_temporaries(target: str | os.PathLike[str]) -> list[Path]:
    """Delete the temporary files that writers of ``target`` on this host left when they
    were killed (their process no longer runs); returns the paths removed."""
    target = Path(os.fspath(target))
    pattern = re.compile(
        rf"^\.{re.escape(target.name)}\.tmp-{re.escape(_host_tag())}-(\d+)-[0-9a-f]{{16}}$"
    )
    removed: list[Path] = []
    try:
        entries = list(target.parent.iterdir())
    except OSError:
        return removed
    for entry in entries:
        match = pattern.match(entry.name)
        if match is None or int(match.group(1)) == os.getpid():
            continue
        if _process_is_gone(int(match.group(1))):
            try:
                entry.unlink()
            except OSError:
                continue
            removed.append(entry)
    return removed


def atomic_write(
    target: str | os.PathLike[str],
    write: Callable[[Path], None],
    *,
    overwrite: bool = False,
    prepare: Callable[[Path], None] | None = None,
    on_failure: Callable[[], None] | None = None,
) -> Path:
    """Write ``target`` atomically: ``write(temporary)``, flush to disk, then publish.

    The temporary file is in the target's directory (named by :func:`temporary_name`;
    stale ones of the same target are removed first). It is published by a hard link when
    ``overwrite`` is false, which fails if the target appeared meanwhile (so of two
    concurrent writers of a new file exactly one succeeds and an existing file is never
    replaced), and by ``os.replace`` otherwise. On any failure the temporary file is
    removed and a previous file at ``target`` is left unchanged. While ``write`` runs, the
    disk is asked to start writing what it has written so far
    (:class:`~cellcoadd.io._files.writeback.EarlyWriteback`), so the final flush waits for less.

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
        (:func:`~cellcoadd.io._files.disk_space.disk_full_error`).
    """
    gate_write(target)
    target = Path(os.fspath(target))
    if target.exists() and not overwrite:
        raise exists_error(target)
    directory = target.parent
    if not directory.is_dir():
        raise CellCoaddFileNotFoundError(f"{directory}: no such directory", path=directory)
    remove_stale_temporaries(target)
    temporary = directory / temporary_name(target)
    if prepare is not None:
        prepare(temporary)
    try:
        with EarlyWriteback(temporary):  # the disk starts writing while write() computes
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
