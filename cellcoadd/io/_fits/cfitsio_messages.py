"""Workaround for CFITSIO's process-wide error-message stack (see
:func:`clear_cfitsio_messages`)."""

from __future__ import annotations

import os

import fitsio

#: A path no file can have (a file is not a directory), opened to drain CFITSIO messages.
_NO_SUCH_FITS_FILE = os.path.join(os.devnull, "cellcoadd-no-such-file.fits")


def clear_cfitsio_messages() -> None:
    """Empty CFITSIO's process-wide stack of error messages.

    fitsio takes messages off that stack only when it raises an error, and only as many as
    fit its 1 kB buffer. What a damaged file leaves there (any bytes, from its corrupted
    header) is then attached to the next, unrelated CFITSIO error, which fitsio cannot
    decode: even opening an intact file would fail. fitsio has no call to clear the stack,
    so it is drained by failing to open a file that cannot exist until an error comes back
    short (the stack was empty).
    """
    for _ in range(8):
        try:
            fitsio.FITS(_NO_SUCH_FITS_FILE).close()
        except UnicodeDecodeError:  # undecodable leftovers, now removed: drain on
            continue
        except OSError as err:
            if len(str(err)) < 512:
                return
            continue
        return
