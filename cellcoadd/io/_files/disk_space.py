"""Disk-space checks of writes: refuse a write that cannot fit, and recognise a failure
caused by a full disk (see :func:`disk_full_error`)."""

from __future__ import annotations

import errno
import os

from cellcoadd.errors import CellCoaddOSError

#: Free space (bytes) below which a failed write is blamed on a full disk.
DISK_FULL_MARGIN = 1 << 20


def check_free_space(target: str | os.PathLike[str], needed: int) -> None:
    """Refuse to start a write of about ``needed`` bytes that cannot fit on the disk.

    Writing into a full disk is worse than refusing up front: HDF5 2.0 cannot close a file
    whose flush failed (the process then crashes at exit) and CFITSIO reports unrelated
    errors. File systems that report no size at all (some network mounts) are not checked.

    Raises
    ------
    OSError
        ``errno.ENOSPC``, naming ``target`` and the space needed and free.
    """
    directory = os.path.dirname(os.path.abspath(target))
    try:
        stats = os.statvfs(directory)
    except (OSError, AttributeError):  # no statvfs on this platform or mount
        return
    if stats.f_blocks == 0:
        return
    free = stats.f_bavail * stats.f_frsize
    if free < needed:
        raise CellCoaddOSError(
            f"disk full: writing needs up to {needed} bytes but only {free} are free in "
            f"{directory}; nothing was written",
            errno=errno.ENOSPC,
            path=target,
        )


def disk_full_error(target: str | os.PathLike[str], error: BaseException) -> OSError | None:
    """A clear ``ENOSPC`` error if ``error`` (raised while writing ``target``) came from a
    full disk or exhausted quota, else None.

    CFITSIO does not pass the system error on, so a failure while the target's file
    system has less than :data:`DISK_FULL_MARGIN` free is taken to be a full disk too.
    Call this before removing the partial file, whose blocks are part of the evidence.
    """
    code = getattr(error, "errno", None)
    text = str(error)
    full = code in (errno.ENOSPC, errno.EDQUOT) or any(
        phrase in text for phrase in ("No space left on device", "Disk quota exceeded")
    )
    directory = os.path.dirname(os.path.abspath(target))
    free: int | None = None
    try:
        stats = os.statvfs(directory)
        if stats.f_blocks > 0:
            free = stats.f_bavail * stats.f_frsize
    except (OSError, AttributeError):
        pass
    if not full and (free is None or free >= DISK_FULL_MARGIN):
        return None
    where = f"{directory} has {free} bytes free" if free is not None else directory
    return CellCoaddOSError(
        f"disk full or quota exceeded while writing ({where}); nothing was written and any "
        f"previous file is unchanged [{type(error).__name__}: {_first_line(text)}]",
        errno=errno.ENOSPC,
        path=target,
    )


def _first_line(text: str) -> str:
    return text.strip().splitlines()[0] if text.strip() else ""
