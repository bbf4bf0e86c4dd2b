"""The exception hierarchy: every error cellcoadd raises on purpose is a :class:`CellCoaddError`.

Which class to raise
--------------------
Pick the most specific class that fits; its builtin base (``ValueError``, ``TypeError``, ...)
is kept as a mixin, so ``except ValueError`` written against older versions still works.

- A caller passed an argument of the right type with a bad value:
  :class:`CellCoaddValueError` (``value=``, ``allowed=``); a number outside its interval:
  :class:`CellCoaddRangeError` (``value=``, ``low=``, ``high=``); arguments that are each
  fine but cannot be used together: :class:`CellCoaddIncompatibleValuesError` (``values=``).
- An argument of the wrong type: :class:`CellCoaddTypeError` (``value=``, ``allowed=``).
- A name that is not known (a mask bit, a column, a plane): :class:`CellCoaddKeyError`
  (``value=`` the key, ``allowed=`` the known ones); an index outside a grid (a patch of a
  tract, a tract of a sky map): :class:`CellCoaddIndexError`.
- Boxes, cells, patches, tracts or sky maps that cannot be formed: :class:`GeometryError`.
- Build, storage or validation settings that cannot work: :class:`ConfigError`.
- A file that cannot be read (damaged, truncated, not ours, a newer major version) or written
  as asked: :class:`CellCoaddFormatError` (always names the file; ``hdu=`` when known).
  A file that does not exist: :class:`CellCoaddFileNotFoundError`; one a write would
  replace without ``overwrite=True``: :class:`CellCoaddFileExistsError`; the disk is full or
  another operating-system failure: :class:`CellCoaddOSError` (``errno=``). A parsing helper
  that finds stored bytes, a header or an HDF5 object damaged but does not know the file
  raises :class:`DamagedDataError` (``hdu=`` when known); the reader's guard
  (``io/_files/read_checks.py``) re-raises it as a :class:`CellCoaddFormatError` naming the
  file. Readers never signal damage with a builtin exception.
- An in-memory coadd that is malformed: :class:`InvalidCoaddError`.
- An input exposure that cannot be used: :class:`InputError`, or its :class:`ExposureError`
  (malformed at construction), :class:`PsfError` (the PSF cannot be drawn) and
  :class:`IndexRowError` (an exposure-index row that disagrees with its checksum or its
  file: ``row=``, ``fields=``); a PSF
  description that cannot be encoded or decoded: :class:`PsfCodecError`.
- A build that cannot proceed: :class:`BuildError`; one cell failed: :class:`CellBuildError`;
  a pixel mapping out of tolerance: :class:`MappingError`.
- A tract run whose patches failed: :class:`TractRunError` (names them and why); another
  run holds its output directory: :class:`RunLockedError` (names the holder).
- A shear measurement that cannot run: :class:`ShearError`, or :class:`MetacalError`,
  :class:`BfdError`, :class:`EmptyCellError` (a cell without inputs).
- A computation that failed although its inputs were valid (a sampler that does not
  converge, a self-check of a pipeline): :class:`CellCoaddRuntimeError`; one that produced
  non-finite numbers where finite ones are required: :class:`CellCoaddFloatingPointError`.
- An optional dependency that is not installed: :class:`MissingDependencyError` (the
  message names the extra to install).
- A feature that is not supported here: :class:`CellCoaddNotImplementedError`. A bare
  ``raise NotImplementedError`` is kept only as the body of an abstract method;
  ``AttributeError`` only where Python's protocols ask for it (module ``__getattr__``,
  descriptors). No other builtin exception is raised directly (``tests/test_errors.py``).

Raised inside a pydantic validator, an error that is a ``ValueError`` reaches the caller
wrapped in pydantic's ``ValidationError`` (itself a ``ValueError``); the original is in
its ``errors()[i]["ctx"]["error"]``.

Facts as attributes
-------------------
Every error takes the facts it is about as keyword arguments and keeps them as attributes,
``None`` when not given: ``path`` (a file), ``hdu`` (index or name), ``visit`` and ``detector``
(an exposure), ``cell`` (an ``(x, y)`` cell index). The value classes add ``value`` and
``allowed``. The message stays the human-readable sentence (it still names those facts, as
before); :attr:`CellCoaddError.facts` lists the facts that were given. Errors pickle with
their facts (they cross process boundaries in parallel builds)::

    raise CellCoaddRangeError(
        f"psf_size must be in [3, 201], got {size}", value=size, low=3, high=201
    )

::

    CellCoaddError
    ├── CellCoaddValueError (ValueError)      a bad argument value
    │   ├── CellCoaddRangeError               a number outside its interval
    │   ├── CellCoaddIncompatibleValuesError  arguments that cannot be used together
    │   ├── GeometryError                     boxes, cells, patches, tracts, sky maps
    │   ├── ConfigError                       settings that cannot work together
    │   ├── InvalidCoaddError                 an in-memory coadd is malformed
    │   ├── InputError                        an input exposure is unusable
    │   │   ├── ExposureError                 ... malformed at construction
    │   │   ├── PsfError                      ... its PSF model cannot be drawn
    │   │   └── IndexRowError                 ... its index row disagrees with the file
    │   ├── PsfCodecError                     a PSF description cannot be encoded/decoded
    │   └── ShearError                        a shear measurement cannot run
    │       ├── MetacalError                  ... metacalibration
    │       ├── BfdError                      ... BFD moments or shear
    │       └── EmptyCellError                ... a cell without inputs
    ├── CellCoaddTypeError (TypeError)        an argument of the wrong type
    ├── CellCoaddKeyError (KeyError)          an unknown name
    ├── CellCoaddIndexError (IndexError)      an index outside a grid
    ├── CellCoaddFormatError                  a file cannot be read or written as asked
    ├── DamagedDataError (ValueError)         stored data are damaged (file not yet named)
    ├── CellCoaddOSError (OSError)            the operating system refused (disk full, ...)
    │   ├── CellCoaddFileNotFoundError        a file or directory does not exist
    │   └── CellCoaddFileExistsError          a write would replace a file
    ├── BuildError                            a build cannot proceed
    │   ├── CellBuildError (RuntimeError)     one cell failed (names the cell, traceback)
    │   └── MappingError (ValueError)         a pixel mapping out of tolerance
    ├── TractRunError                         patches of a tract run failed (names them)
    │   └── RunLockedError                    another run holds the output directory
    ├── CellCoaddRuntimeError (RuntimeError)  a computation failed on valid inputs
    ├── CellCoaddFloatingPointError           non-finite results (FloatingPointError)
    ├── MissingDependencyError (ImportError)  an optional dependency is not installed
    └── CellCoaddNotImplementedError          a feature not supported here

Warnings: :class:`PsfStampWarning`, a coadd PSF stamp that leaves out too much of the flux.
"""

from __future__ import annotations

import os
from typing import Any

__all__ = [
    "BfdError",
    "PsfStampWarning",
    "BuildError",
    "CellBuildError",
    "CellCoaddError",
    "CellCoaddFileExistsError",
    "CellCoaddFileNotFoundError",
    "CellCoaddFloatingPointError",
    "CellCoaddFormatError",
    "CellCoaddIncompatibleValuesError",
    "CellCoaddIndexError",
    "CellCoaddKeyError",
    "CellCoaddNotImplementedError",
    "CellCoaddOSError",
    "CellCoaddRangeError",
    "CellCoaddRuntimeError",
    "CellCoaddTypeError",
    "CellCoaddValueError",
    "ConfigError",
    "DamagedDataError",
    "EmptyCellError",
    "ExposureError",
    "GeometryError",
    "IndexRowError",
    "InputError",
    "InvalidCoaddError",
    "MappingError",
    "MetacalError",
    "MissingDependencyError",
    "PsfCodecError",
    "PsfError",
    "RunLockedError",
    "ShearError",
    "TractRunError",
]

#: the facts every error may carry, in the order :attr:`CellCoaddError.facts` lists them
_COMMON_FACTS = ("path", "hdu", "visit", "detector", "cell")


def _rebuild(cls: type[BaseException], args: tuple[Any, ...], state: dict[str, Any]) -> Any:
    """Unpickle an error without calling its ``__init__`` (whose signature varies)."""
    error = cls.__new__(cls, *args)
    error.args = args
    for name, value in state.items():
        setattr(error, name, value)  # setattr, not __dict__: OSError keeps errno in slots
    return error


class CellCoaddError(Exception):
    """Root of cellcoadd's errors.

    Parameters
    ----------
    message : str
        The sentence shown to the user; ``str(error)`` returns it unchanged.
    path : str or os.PathLike, optional
        The file the error is about (stored as ``str``).
    hdu : int or str, optional
        The HDU (index or EXTNAME) or HDF5 object name within ``path``.
    visit, detector : int, optional
        The exposure the error is about.
    cell : tuple of int, optional
        The ``(x, y)`` index of the cell the error is about.
    """

    path: str | None
    hdu: int | str | None
    visit: int | None
    detector: int | None
    cell: tuple[int, int] | None

    def __init__(
        self,
        message: str = "",
        *,
        path: str | os.PathLike[str] | None = None,
        hdu: int | str | None = None,
        visit: int | None = None,
        detector: int | None = None,
        cell: tuple[int, int] | None = None,
    ) -> None:
        super().__init__(message)
        self.path = None if path is None else os.fspath(path)
        self.hdu = hdu
        self.visit = visit
        self.detector = detector
        self.cell = None if cell is None else (int(cell[0]), int(cell[1]))

    @property
    def facts(self) -> dict[str, Any]:
        """The facts given as keywords (those that are not ``None``), by name."""
        # getattr for the common facts: ImportError keeps ``path`` in a slot, not in vars()
        facts = {name: getattr(self, name) for name in _COMMON_FACTS}
        facts.update(vars(self))
        return {name: value for name, value in facts.items() if value is not None}

    def __reduce__(self) -> tuple[Any, ...]:
        state = {name: getattr(self, name) for name in _COMMON_FACTS}
        state.update(vars(self))
        if isinstance(self, ImportError):
            state["name"] = self.name
        if isinstance(self, OSError):  # its slots; a None left unset keeps OSError's text
            slots = {"errno": self.errno, "strerror": self.strerror, "filename": self.filename}
            state.update({name: value for name, value in slots.items() if value is not None})
        return (_rebuild, (type(self), self.args, state))


# -- argument values -------------------------------------------------------------------


class _ValueFacts(CellCoaddError):
    """Base of the errors about one value: ``value`` is it, ``allowed`` what would do."""

    def __init__(
        self, message: str = "", *, value: Any = None, allowed: Any = None, **facts: Any
    ) -> None:
        super().__init__(message, **facts)
        self.value = value
        self.allowed = allowed


class CellCoaddValueError(_ValueFacts, ValueError):
    """An argument has the right type but a value that cannot be used.

    Parameters
    ----------
    message : str
        The sentence shown to the user.
    value : object, optional
        The value at fault.
    allowed : object, optional
        What would have been accepted (a collection of values, or a description).
    **facts
        ``path``, ``hdu``, ``visit``, ``detector``, ``cell`` as for :class:`CellCoaddError`.
    """


class CellCoaddRangeError(CellCoaddValueError):
    """A number lies outside its interval ``[low, high]`` (an open end is ``None``).

    ``allowed`` is set to ``(low, high)``; the message says whether an end is excluded.
    """

    def __init__(
        self,
        message: str = "",
        *,
        value: Any = None,
        low: Any = None,
        high: Any = None,
        **facts: Any,
    ) -> None:
        allowed = None if low is None and high is None else (low, high)
        super().__init__(message, value=value, allowed=allowed, **facts)
        self.low = low
        self.high = high


class CellCoaddIncompatibleValuesError(CellCoaddValueError):
    """Arguments each valid on their own cannot be used together.

    ``values`` maps each argument's name to the value given.
    """

    def __init__(
        self, message: str = "", *, values: dict[str, Any] | None = None, **facts: Any
    ) -> None:
        super().__init__(message, **facts)
        self.values = values


class GeometryError(CellCoaddValueError):
    """Boxes, cells, patches, tracts or sky maps that cannot be formed as asked."""


class ConfigError(CellCoaddValueError):
    """Build, storage or validation settings that cannot work (names the setting)."""


class InvalidCoaddError(CellCoaddValueError):
    """A cell or patch coadd is malformed (raised at construction, naming the field at fault)."""


class InputError(CellCoaddValueError):
    """An input exposure cannot be used; names it by visit and detector."""


class IndexRowError(InputError):
    """A row of the exposure index disagrees with its checksum or with the file it
    describes: ``path`` is the file, ``row`` the row id, ``fields`` the stored fields
    that differ (empty when only the checksum says so)."""

    def __init__(
        self,
        message: str = "",
        *,
        row: int | None = None,
        fields: tuple[str, ...] = (),
        **facts: Any,
    ) -> None:
        super().__init__(message, **facts)
        self.row = row
        self.fields = tuple(fields)


class ExposureError(InputError):
    """An exposure is malformed (raised at construction with the visit and detector)."""


class PsfError(InputError):
    """The PSF model of an exposure cannot be drawn (a rejection ``"bad_psf"`` in a build)."""


class PsfCodecError(CellCoaddValueError):
    """A PSF description cannot be encoded or is not a valid description."""


class ShearError(CellCoaddValueError):
    """A shear measurement cannot run on the given inputs."""


class MetacalError(ShearError):
    """Metacalibration cannot run on the given images."""


class BfdError(ShearError):
    """BFD moments or shear cannot be computed from the given inputs."""


class EmptyCellError(ShearError):
    """A measurement was asked of a cell that has no inputs."""


# -- types, names, indices ---------------------------------------------------------------


class CellCoaddTypeError(_ValueFacts, TypeError):
    """An argument has the wrong type; ``value`` is it, ``allowed`` the accepted types."""


class CellCoaddKeyError(_ValueFacts, KeyError):
    """A name is not known; ``value`` is the name, ``allowed`` the known names.

    Unlike a plain ``KeyError``, ``str(error)`` is the message without added quotes.
    """

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class CellCoaddIndexError(_ValueFacts, IndexError):
    """An index lies outside a grid; ``value`` is the index, ``allowed`` the valid range."""


# -- files ---------------------------------------------------------------------------------


class CellCoaddFormatError(CellCoaddError):
    """A file is not a readable cellcoadd (or exposure) file: names the file and the problem.

    Parameters
    ----------
    path : str or os.PathLike
        The file; the message is ``"{path}: {problem}"``.
    problem : str
        What is wrong with it.
    **facts
        ``hdu``, ``visit``, ``detector``, ``cell`` as for :class:`CellCoaddError`.
    """

    path: str

    def __init__(self, path: str | os.PathLike[str], problem: str, **facts: Any) -> None:
        path = os.fspath(path)
        problem = _one_line_without(problem, path)
        super().__init__(f"{path}: {problem}", path=path, **facts)
        self.problem = problem


def _one_line_without(problem: str, path: str) -> str:
    """``problem`` on one line, without the lines that only repeat ``path`` (CFITSIO's
    messages name the file on lines of their own, several times)."""
    if "\n" not in problem:
        return problem
    names = {path, os.path.abspath(path), os.path.realpath(path)}
    kept: list[str] = []
    for line in (line.strip() for line in problem.splitlines()):
        if line in names:
            if kept and kept[-1].endswith(":"):
                kept[-1] = kept[-1][:-1]
        elif line in {")", "]"} and kept:
            kept[-1] += line
        elif line:
            kept.append(line)
    return "; ".join(kept)


class DamagedDataError(CellCoaddError, ValueError):
    """Bytes, a header or an HDF5 object read from a file are not what the format requires.

    Raised by parsing helpers that do not know which file they read; the reader's guard
    turns it into a :class:`CellCoaddFormatError` naming the file (keeping ``hdu`` and
    ``cell``). Seen outside a reader only when such a helper is called directly.
    """


class CellCoaddOSError(CellCoaddError, OSError):
    """The operating system refused (a full disk, a quota, permissions).

    With ``errno`` given, ``errno``, ``strerror`` (the message) and ``filename`` (``path``)
    are set as for :class:`OSError`, and so is its ``[Errno N] message: 'path'`` text.
    """

    def __init__(self, message: str = "", *, errno: int | None = None, **facts: Any) -> None:
        super().__init__(message, **facts)
        if errno is not None:  # OSError's own parsing of (errno, strerror, filename)
            if self.path is None:
                OSError.__init__(self, errno, message)
            else:
                OSError.__init__(self, errno, message, self.path)


class CellCoaddFileNotFoundError(CellCoaddOSError, FileNotFoundError):
    """A file or directory that should exist does not (``path`` names it)."""


class CellCoaddFileExistsError(CellCoaddOSError, FileExistsError):
    """A write would replace the file ``path`` but ``overwrite=True`` was not given."""


# -- builds and computations ----------------------------------------------------------------


class BuildError(CellCoaddError):
    """A build cannot proceed."""


class CellBuildError(BuildError, RuntimeError):
    """Building one cell failed; the message names the cell and holds the traceback."""


class MappingError(BuildError, CellCoaddValueError):
    """The cell -> exposure pixel mapping cannot be computed within the tolerance."""


class TractRunError(CellCoaddError):
    """A tract run could not build every patch (names the failed patches and why)."""


class RunLockedError(TractRunError):
    """Another run holds the output directory's lock (names the directory and the holder)."""


class CellCoaddRuntimeError(CellCoaddError, RuntimeError):
    """A computation failed although its inputs were valid (no convergence, a self-check)."""


class CellCoaddFloatingPointError(CellCoaddError, FloatingPointError):
    """A computation produced non-finite numbers where finite ones are required."""


class MissingDependencyError(CellCoaddError, ImportError):
    """An optional dependency is not installed; the message says which extra to install.

    ``package`` (also :attr:`ImportError.name`) is the module that could not be imported.
    """

    def __init__(self, message: str = "", *, package: str | None = None, **facts: Any) -> None:
        super().__init__(message, **facts)
        self.name = package

    @property
    def package(self) -> str | None:
        """The module that could not be imported."""
        return self.name


class CellCoaddNotImplementedError(CellCoaddError, NotImplementedError):
    """A feature that is not supported here (the message says what to use instead)."""


class PsfStampWarning(UserWarning):
    """A coadd PSF stamp leaves out more of the PSF's flux than it should (names the cell
    and the fraction outside the stamp); the stamp is renormalised to unit sum."""
