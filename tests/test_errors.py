"""The error hierarchy: exported, picklable with its facts, builtin bases kept as mixins."""

from __future__ import annotations

import errno
import inspect
import pickle

import pytest

import cellcoadd
import cellcoadd.errors as errors_module
from cellcoadd.errors import (
    CellCoaddError,
    CellCoaddFileNotFoundError,
    CellCoaddFormatError,
    CellCoaddIncompatibleValuesError,
    CellCoaddKeyError,
    CellCoaddOSError,
    CellCoaddRangeError,
    CellCoaddValueError,
    ExposureError,
    MappingError,
)

ERROR_CLASSES = [
    obj
    for name, obj in vars(errors_module).items()
    if inspect.isclass(obj) and issubclass(obj, BaseException) and not name.startswith("_")
]

FACTS = {"path": "/data/visit_123.fits", "hdu": "SCI", "visit": 123, "detector": 45, "cell": (3, 7)}


def _make(cls: type[CellCoaddError]) -> CellCoaddError:
    """An instance with every common fact, built through the class's own signature."""
    if issubclass(cls, CellCoaddFormatError):
        facts = {key: value for key, value in FACTS.items() if key != "path"}
        return cls(FACTS["path"], "the file ends inside a header", **facts)
    return cls("visit 123, detector 45, cell (3, 7): something is wrong", **FACTS)


def test_every_error_class_is_exported_and_under_the_root() -> None:
    assert len(ERROR_CLASSES) >= 20
    for cls in ERROR_CLASSES:
        assert cls.__module__ == "cellcoadd.errors"
        assert issubclass(cls, CellCoaddError), cls
        assert cls.__name__ in errors_module.__all__, cls
        assert cls.__name__ in cellcoadd.__all__, cls
        assert getattr(cellcoadd, cls.__name__) is cls
    assert sorted(errors_module.__all__) == sorted(cls.__name__ for cls in ERROR_CLASSES)


def test_moved_classes_have_one_home() -> None:
    from cellcoadd.io.exposures import psf_codec
    from cellcoadd.shear import bfd, bfd_moments

    assert bfd.BfdError is errors_module.BfdError  # the public BFD facade re-exports it
    assert psf_codec.PsfCodecError is errors_module.PsfCodecError
    assert "BfdError" not in bfd_moments.__all__


@pytest.mark.parametrize("cls", ERROR_CLASSES, ids=lambda cls: cls.__name__)
def test_pickle_round_trip_keeps_class_message_and_facts(cls: type[CellCoaddError]) -> None:
    error = _make(cls)
    copy = pickle.loads(pickle.dumps(error))
    assert type(copy) is cls
    assert str(copy) == str(error)
    assert copy.args == error.args
    assert copy.facts == error.facts
    for name, value in FACTS.items():
        assert getattr(copy, name) == value, name


def test_message_is_unchanged_and_facts_are_attributes() -> None:
    error = CellCoaddRangeError(
        "psf_size must be in [3, 201], got 401", value=401, low=3, high=201, cell=(1, 2)
    )
    assert str(error) == "psf_size must be in [3, 201], got 401"
    assert (error.value, error.low, error.high, error.allowed) == (401, 3, 201, (3, 201))
    assert error.cell == (1, 2) and error.path is None and error.visit is None
    assert error.facts == {"cell": (1, 2), "value": 401, "allowed": (3, 201), "low": 3, "high": 201}
    copy = pickle.loads(pickle.dumps(error))
    assert (copy.value, copy.low, copy.high) == (401, 3, 201)
    values = {"variance_hdu": 2, "weight_hdu": 3}
    both = CellCoaddIncompatibleValuesError("give one of them", values=values)
    assert pickle.loads(pickle.dumps(both)).values == values


def test_format_error_names_the_file() -> None:
    error = CellCoaddFormatError("/data/coadd.fits", "truncated", hdu=4)
    assert str(error) == "/data/coadd.fits: truncated"
    assert (error.path, error.problem, error.hdu) == ("/data/coadd.fits", "truncated", 4)


def test_key_error_message_has_no_added_quotes() -> None:
    error = CellCoaddKeyError("unknown mask bit 'SAT'", value="SAT", allowed=["BAD"])
    assert str(error) == "unknown mask bit 'SAT'"
    with pytest.raises(KeyError):
        raise error


def test_os_errors_keep_errno_and_text() -> None:
    full = CellCoaddOSError("disk full", errno=errno.ENOSPC, path="/scratch/out.h5")
    assert str(full) == str(OSError(errno.ENOSPC, "disk full", "/scratch/out.h5"))
    assert full.errno == errno.ENOSPC and full.filename == "/scratch/out.h5"
    copy = pickle.loads(pickle.dumps(full))
    assert (copy.errno, copy.filename, str(copy)) == (full.errno, full.filename, str(full))
    missing = CellCoaddFileNotFoundError("/data/x.fits: no such file", path="/data/x.fits")
    assert str(pickle.loads(pickle.dumps(missing))) == "/data/x.fits: no such file"
    assert isinstance(missing, FileNotFoundError) and missing.path == "/data/x.fits"


@pytest.mark.parametrize(
    ("cls", "builtin"),
    [
        (CellCoaddValueError, ValueError),
        (CellCoaddRangeError, ValueError),
        (ExposureError, ValueError),
        (MappingError, ValueError),
        (errors_module.ConfigError, ValueError),
        (errors_module.InvalidCoaddError, ValueError),
        (errors_module.PsfCodecError, ValueError),
        (errors_module.BfdError, ValueError),
        (errors_module.MetacalError, ValueError),
        (errors_module.EmptyCellError, ValueError),
        (errors_module.GeometryError, ValueError),
        (errors_module.CellCoaddTypeError, TypeError),
        (errors_module.CellCoaddKeyError, KeyError),
        (errors_module.CellCoaddIndexError, IndexError),
        (errors_module.CellBuildError, RuntimeError),
        (errors_module.CellCoaddRuntimeError, RuntimeError),
        (errors_module.CellCoaddNotImplementedError, NotImplementedError),
        (errors_module.CellCoaddFloatingPointError, FloatingPointError),
        (CellCoaddOSError, OSError),
        (CellCoaddFileNotFoundError, FileNotFoundError),
    ],
)
def test_builtin_bases_still_catch(cls: type[CellCoaddError], builtin: type[Exception]) -> None:
    with pytest.raises(builtin):
        raise _make(cls)
