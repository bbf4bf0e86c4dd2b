"""The one gate every path the library opens goes through (readers and writers).

A path is refused (:class:`~cellcoadd.errors.CellCoaddFormatError` naming it) when:

* it is empty, or holds a NUL byte;
* for FITS files, CFITSIO would read part of its name as extended syntax instead of a
  file name, before or after resolving symbolic links: ``[filter]``, ``(template)``,
  ``scheme://`` (``mem://``, ``http://``, ...), a ``+N`` HDU suffix (``e.fits+1`` would
  read ``e.fits``), trailing blanks (:func:`cellcoadd.io._fits.paths.cfitsio_syntax`);
  leading ``!``, ``-`` or blanks are harmless because CFITSIO is given the resolved
  absolute path;
* (reading) it does not resolve to a non-empty *regular* file: FIFOs, devices (a symlink
  to ``/dev/zero``), sockets and directories are refused without being opened, so a read
  neither hangs nor grows without bound; a stated ``max_bytes`` bounds the size;
* (writing) the target exists and is not a regular file (a FIFO would block the final
  rename's readers, a device would be replaced by our file);
* (creating or updating in place: a SQLite database, a lock, ``cellcoadd init``'s files)
  the name itself is a symbolic link, dangling or not (:func:`gate_create`): writing
  through it would create or change its target, which may lie outside the folder.

:func:`open_nofollow` opens such a file for reading and writing with ``O_NOFOLLOW`` and
``O_NONBLOCK``, and checks the open descriptor is a regular file.

:func:`read_bytes` reads a small file whole through the gate, opening it non-blocking and
checking the open descriptor again, so a file swapped for a FIFO after the check cannot
hang the read.
"""

from __future__ import annotations

import errno
import os
import stat

from cellcoadd.errors import CellCoaddFileNotFoundError, CellCoaddFormatError
from cellcoadd.io._fits.paths import cfitsio_syntax

PathLike = str | os.PathLike[str]

_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def _kind(mode: int) -> str:
    for test, name in _KINDS:
        if test(mode):
            return name
    return "not a regular file"


def _name(path: PathLike) -> str:
    try:
        name = os.fspath(path)
    except TypeError:
        raise CellCoaddFormatError(repr(path), "not a path") from None
    if isinstance(name, bytes):
        name = os.fsdecode(name)
    if not name:
        raise CellCoaddFormatError("", "empty path")
    if "\0" in name:
        raise CellCoaddFormatError(name.replace("\0", "\\0"), "a path must not hold NUL bytes")
    return name


def _check_fits_name(name: str, resolved: str) -> None:
    for candidate in (name, resolved):
        reason = cfitsio_syntax(candidate)
        if reason is not None:
            where = "" if candidate == name else f" (resolved to {resolved})"
            raise CellCoaddFormatError(name, f"refused{where}: {reason}")


def gate_read(
    path: PathLike, *, what: str = "file", fits: bool = False, max_bytes: int | None = None
) -> str:
    """The resolved absolute path of the regular file ``path`` refers to, checked.

    Parameters
    ----------
    path : path-like
        What the caller was given.
    what : str
        What the file is, for messages ("manifest", "PSF model file", ...).
    fits : bool
        Whether CFITSIO will open it (then its extended syntax is refused).
    max_bytes : int, optional
        Largest size accepted.

    Raises
    ------
    FileNotFoundError
        When nothing is at ``path`` (or a symlink points nowhere).
    CellCoaddFormatError
        See the module docstring; the message names ``path``.
    """
    name = _name(path)
    resolved = os.path.realpath(name)
    if fits:
        _check_fits_name(name, resolved)
    try:
        info = os.stat(resolved)
    except FileNotFoundError:
        raise CellCoaddFileNotFoundError(
            f"{name}: no such {what}", errno=errno.ENOENT, path=name
        ) from None
    except OSError as err:
        raise CellCoaddFormatError(name, f"cannot access the {what} ({err.strerror})") from None
    if not stat.S_ISREG(info.st_mode):
        target = "" if resolved == os.path.abspath(name) else f" (resolves to {resolved})"
        raise CellCoaddFormatError(
            name, f"the {what} is {_kind(info.st_mode)}{target}, not a regular file"
        )
    if info.st_size == 0:
        raise CellCoaddFormatError(name, f"the {what} is empty")
    if max_bytes is not None and info.st_size > max_bytes:
        raise CellCoaddFormatError(
            name, f"the {what} has {info.st_size} bytes, more than the {max_bytes} accepted"
        )
    return resolved


def gate_write(path: PathLike, *, what: str = "file", fits: bool = False) -> str:
    """The resolved absolute path a writer may replace (atomically) for ``path``.

    The directory must exist; an existing target (after symlinks) must be a regular file.

    Raises
    ------
    CellCoaddFormatError
        See the module docstring.
    """
    name = _name(path)
    resolved = os.path.realpath(name)
    if fits:
        _check_fits_name(name, resolved)
    try:
        info = os.stat(resolved)
    except FileNotFoundError:
        return resolved
    except OSError as err:
        raise CellCoaddFormatError(name, f"cannot access the {what} ({err.strerror})") from None
    if not stat.S_ISREG(info.st_mode):
        raise CellCoaddFormatError(
            name, f"refused to write over {_kind(info.st_mode)}: not a regular file"
        )
    return resolved


def gate_create(path: PathLike, *, what: str = "file", companions: tuple[str, ...] = ()) -> str:
    """The absolute path of a file a writer creates or changes in place at ``path`` itself.

    Unlike :func:`gate_write` (whose atomic rename replaces a link, never its target),
    the name is not resolved: a symbolic link there, dangling or not, is refused, as is
    anything but a regular file, before anything opens it. The folders above it may be
    links (only the last component is checked, as ``O_NOFOLLOW`` does).

    Parameters
    ----------
    path : path-like
        The file (it need not exist).
    what : str
        What the file is, for messages ("run ledger", ...).
    companions : tuple of str
        Suffixes of files the writer also creates next to it, checked the same way
        (SQLite's ``"-journal"``, ``"-wal"``, ``"-shm"``).

    Raises
    ------
    CellCoaddFormatError
        Naming ``path`` (or the companion) and what is there.
    """
    name = _name(path)
    for candidate in (name, *(name + suffix for suffix in companions)):
        try:
            info = os.lstat(candidate)
        except FileNotFoundError:
            continue
        except OSError as err:
            raise CellCoaddFormatError(
                candidate, f"cannot access the {what} ({err.strerror})"
            ) from None
        if stat.S_ISLNK(info.st_mode):
            raise CellCoaddFormatError(
                candidate,
                f"refused: a symbolic link (to {os.readlink(candidate)}) where the {what} "
                "is written; it is never written through a link: remove the link",
            )
        if not stat.S_ISREG(info.st_mode):
            raise CellCoaddFormatError(
                candidate,
                f"refused: {_kind(info.st_mode)} where the {what} is written, not a regular file",
            )
    return os.path.abspath(name)


def open_nofollow(path: PathLike, *, what: str = "file", mode: int = 0o644) -> int:
    """A read-write descriptor of the regular file ``path`` itself, created when missing.

    Opened with ``O_NOFOLLOW`` (a symbolic link is refused, never followed) and
    ``O_NONBLOCK`` (a FIFO cannot block the open), then checked on the descriptor.

    Raises
    ------
    CellCoaddFormatError
        When ``path`` is a link, not a regular file, or cannot be opened (names it).
    """
    name = _name(path)
    flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | getattr(os, "O_NONBLOCK", 0)
    try:
        descriptor = os.open(name, flags, mode)
    except OSError as err:
        if err.errno == errno.ELOOP:
            gate_create(name, what=what)  # names the link and its target
        raise CellCoaddFormatError(
            name, f"cannot open the {what} ({err.strerror or err})"
        ) from None
    info = os.fstat(descriptor)
    if not stat.S_ISREG(info.st_mode):
        os.close(descriptor)
        raise CellCoaddFormatError(name, f"the {what} is {_kind(info.st_mode)}, not a regular file")
    return descriptor


def read_bytes(path: PathLike, *, what: str, max_bytes: int) -> bytes:
    """The whole content of the small regular file ``path`` (at most ``max_bytes``)."""
    resolved = gate_read(path, what=what, max_bytes=max_bytes)
    name = os.fspath(path)
    try:
        descriptor = os.open(resolved, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as err:
        raise CellCoaddFormatError(name, f"cannot read the {what} ({err.strerror})") from None
    try:
        if not stat.S_ISREG(os.fstat(descriptor).st_mode):  # swapped since the check
            raise CellCoaddFormatError(name, f"the {what} is not a regular file")
        chunks = []
        total = 0
        while total <= max_bytes:
            chunk = os.read(descriptor, min(1 << 20, max_bytes + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
    except OSError as err:
        raise CellCoaddFormatError(name, f"cannot read the {what} ({err.strerror})") from None
    finally:
        os.close(descriptor)
    if total > max_bytes:
        raise CellCoaddFormatError(name, f"the {what} grew beyond {max_bytes} bytes")
    return b"".join(chunks)
