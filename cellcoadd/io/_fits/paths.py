"""File names handed to CFITSIO (through fitsio): never read as its extended syntax.

CFITSIO gives meaning to parts of a file name: a leading ``!`` (overwrite), ``-`` and
``stdin``/``stdout``, leading and trailing blanks (stripped), ``name[filter]``,
``name(template)`` and ``scheme://``. A path such as ``!dir/y.fits`` would read or write
``dir/y.fits`` while our own checks (checksums, existence) look at ``!dir/y.fits``.
:func:`cfitsio_path` is the name every FITS read and write passes to fitsio.
"""

from __future__ import annotations

import os
import re

from cellcoadd.errors import CellCoaddValueError

#: ``name+N``: CFITSIO opens HDU ``N`` of ``name`` (``e.fits+1`` reads ``e.fits``).
_HDU_SUFFIX = re.compile(r"\+\d+\s*$")


def cfitsio_syntax(name: str) -> str | None:
    """Why CFITSIO would not read ``name`` literally as a file name, or None.

    Covers ``name[filter]``, ``name(template)``, ``scheme://`` (``mem://``, URLs), the
    ``name+N`` HDU suffix and trailing blanks (stripped). A leading ``!``, ``-`` or blank
    is made harmless by :func:`cfitsio_path` (or by passing an absolute path).
    """
    if any(char in name for char in "[]()"):
        return "'[', ']', '(' and ')' are CFITSIO extended file-name syntax"
    if "://" in name:
        return "'scheme://' is CFITSIO extended file-name syntax (mem://, URLs)"
    if _HDU_SUFFIX.search(name):
        return "a '+N' suffix is CFITSIO syntax for HDU N of another file"
    if name != name.rstrip():
        return "CFITSIO strips trailing blanks from file names"
    return None


def check_fits_path(path: str | os.PathLike[str]) -> str:
    """Refuse paths that CFITSIO would parse as extended file-name syntax, not as a file.

    See :func:`cfitsio_syntax` (CFITSIO would silently write or read a different file),
    so such FITS paths raise ValueError. A leading ``!`` or blank is made harmless by
    :func:`cfitsio_path` instead.
    """
    name = os.fspath(path)
    reason = cfitsio_syntax(name)
    if reason is not None:
        raise CellCoaddValueError(
            f"{name!r}: FITS paths must be read literally by CFITSIO: {reason}",
            path=name,
            value=name,
        )
    return name


def cfitsio_path(path: str | os.PathLike[str]) -> str:
    """``path`` as a name CFITSIO opens literally (ValueError if it cannot be made so).

    Relative paths get a ``./`` prefix, so a leading ``!``, ``-`` or blank is part of the
    file name rather than CFITSIO syntax (``!dir/y.fits`` -> ``./!dir/y.fits``).
    """
    name = check_fits_path(path)
    if not name:
        raise CellCoaddValueError("empty FITS path", value=name)
    return name if os.path.isabs(name) else os.path.join(".", name)


#: First bytes of every FITS file (the primary header's first card).
FITS_MAGIC = b"SIMPLE  ="


def starts_like_fits(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` starts with a FITS primary header card.

    Checked before CFITSIO opens a file: CFITSIO decompresses gzip, compress and bzip2
    streams into memory whatever their name, so a small compressed file named ``.fits``
    could cost gigabytes before any check of ours runs.
    """
    with open(path, "rb") as stream:
        return stream.read(len(FITS_MAGIC)) == FITS_MAGIC
