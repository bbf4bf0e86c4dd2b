"""The exception hierarchy: every error cellcoadd raises on purpose is a :class:`CellCoaddError`.

::

    CellCoaddError
    ├── CellCoaddFormatError   a file cannot be read or written as asked (names the file)
    ├── ConfigError            settings that cannot work together
    ├── InvalidCoaddError      an in-memory coadd is malformed (names the field)
    ├── InputError             an input exposure is unusable (names visit and detector)
    │   ├── ExposureError      ... malformed at construction
    │   └── PsfError           ... its PSF model cannot be drawn
    ├── BuildError             a build cannot proceed
    │   ├── CellBuildError     one cell failed (names the cell, carries the traceback)
    │   └── MappingError       a pixel mapping cannot be computed within tolerance
    ├── EmptyCellError         a measurement was asked of a cell without inputs
    └── MetacalError           metacalibration cannot run on the given images

Warnings: :class:`PsfStampWarning`, a coadd PSF stamp that leaves out too much of the flux.

Errors that were ``ValueError`` before keep that base too, so existing ``except
ValueError`` clauses still catch them.
"""

from __future__ import annotations

import os


class CellCoaddError(Exception):
    """Root of cellcoadd's errors."""


class CellCoaddFormatError(CellCoaddError):
    """A file is not a readable cellcoadd (or exposure) file: names the file and the problem."""

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        self.path = os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self) -> tuple[type, tuple[str, str]]:  # picklable across processes
        return (type(self), (self.path, self.problem))


class ConfigError(CellCoaddError, ValueError):
    """Build or storage settings that cannot work (names the setting)."""


class InvalidCoaddError(CellCoaddError, ValueError):
    """A cell or patch coadd is malformed (raised at construction, naming the field at fault)."""


class InputError(CellCoaddError, ValueError):
    """An input exposure cannot be used; the message names it by visit and detector."""


class ExposureError(InputError):
    """An exposure is malformed (raised at construction with the visit and detector)."""


class PsfError(InputError):
    """The PSF model of an exposure cannot be drawn (a rejection ``"bad_psf"`` in a build)."""


class BuildError(CellCoaddError):
    """A build cannot proceed."""


class CellBuildError(BuildError, RuntimeError):
    """Building one cell failed; the message names the cell and holds the traceback."""


class MappingError(BuildError, ValueError):
    """The cell -> exposure pixel mapping cannot be computed within the tolerance."""


class EmptyCellError(CellCoaddError, ValueError):
    """A measurement was asked of a cell that has no inputs."""


class MetacalError(CellCoaddError, ValueError):
    """Metacalibration cannot run on the given images."""


class PsfStampWarning(UserWarning):
    """A coadd PSF stamp leaves out more of the PSF's flux than it should (names the cell
    and the fraction outside the stamp); the stamp is renormalised to unit sum."""
