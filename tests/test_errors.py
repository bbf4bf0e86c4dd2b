"""The error hierarchy: exported, picklable with its facts, builtin bases kept as mixins."""

from __future__ import annotations

import ast
import builtins
import errno
import inspect
import json
import pickle
import re
from pathlib import Path
from typing import Any

import h5py
import pytest
from coadd_factory import make_patch

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
from cellcoadd.geometry.box import Box
from cellcoadd.io import api
from cellcoadd.io._files.read_checks import is_file_failure

ERROR_CLASSES = [
    obj
    for name, obj in vars(errors_module).items()
    if inspect.isclass(obj)
    and issubclass(obj, BaseException)
    and not issubclass(obj, Warning)
    and not name.startswith("_")
]
WARNING_CLASSES = [
    obj
    for name, obj in vars(errors_module).items()
    if inspect.isclass(obj) and issubclass(obj, Warning) and not name.startswith("_")
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
    assert sorted(errors_module.__all__) == sorted(
        cls.__name__ for cls in ERROR_CLASSES + WARNING_CLASSES
    )


def test_every_warning_class_is_exported() -> None:
    assert WARNING_CLASSES, "the library's warnings live in errors.py"
    for cls in WARNING_CLASSES:
        assert cls.__name__ in cellcoadd.__all__, cls
        assert getattr(cellcoadd, cls.__name__) is cls


def test_moved_classes_have_one_home() -> None:
    from cellcoadd.io.exposures import psf_codec
    from cellcoadd.shear import bfd
    from cellcoadd.shear.bfd import _moments as bfd_moments

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
        (errors_module.DamagedDataError, ValueError),
        (errors_module.CellCoaddTypeError, TypeError),
        (errors_module.CellCoaddKeyError, KeyError),
        (errors_module.CellCoaddIndexError, IndexError),
        (errors_module.CellBuildError, RuntimeError),
        (errors_module.CellCoaddRuntimeError, RuntimeError),
        (errors_module.CellCoaddNotImplementedError, NotImplementedError),
        (errors_module.CellCoaddFloatingPointError, FloatingPointError),
        (CellCoaddOSError, OSError),
        (CellCoaddFileNotFoundError, FileNotFoundError),
        (errors_module.CellCoaddFileExistsError, FileExistsError),
        (errors_module.MissingDependencyError, ImportError),
    ],
)
def test_builtin_bases_still_catch(cls: type[CellCoaddError], builtin: type[Exception]) -> None:
    with pytest.raises(builtin):
        raise _make(cls)


# -- no builtin exception is raised by the library ------------------------------------------

PACKAGE = Path(cellcoadd.__file__).resolve().parent
BUILTIN_EXCEPTIONS = {
    name
    for name, obj in vars(builtins).items()
    if inspect.isclass(obj) and issubclass(obj, BaseException)
}
#: Functions of Python's attribute protocol (module ``__getattr__``, descriptors), which
#: must raise a plain AttributeError.
ATTRIBUTE_PROTOCOL = re.compile(r"__get__|__getattr__|__getattribute__|getattr_")


def _is_abstract_body(function: ast.AST, node: ast.Raise) -> bool:
    """``raise NotImplementedError`` as the whole body (after a docstring) of a method."""
    if not isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef)):
        return False
    body = function.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        body = body[1:]
    return body == [node]


def builtin_exception_sites(source: str) -> list[tuple[int, str]]:
    """``(line, name)`` of every builtin exception the code raises or builds (``raise
    ValueError(...)``, ``raise KeyError``, ``return OSError(...)``), bar the two allowed:
    ``NotImplementedError`` as the body of an abstract method and ``AttributeError`` in the
    attribute protocol."""
    tree = ast.parse(source)
    parents = {child: parent for parent in ast.walk(tree) for child in ast.iter_child_nodes(parent)}

    def enclosing_function(node: ast.AST) -> ast.AST | None:
        while node in parents:
            node = parents[node]
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                return node
        return None

    sites: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Raise) and isinstance(node.exc, ast.Name):
            name, at = node.exc.id, node  # raise ValueError (no call)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            name, at = node.func.id, node  # ValueError(...) raised, returned or stored
        else:
            continue
        if name not in BUILTIN_EXCEPTIONS:
            continue
        function = enclosing_function(at)
        if name == "NotImplementedError" and function is not None:
            statement = parents.get(at) if isinstance(at, ast.Call) else at
            if isinstance(statement, ast.Raise) and _is_abstract_body(function, statement):
                continue
        if name == "AttributeError" and isinstance(function, ast.FunctionDef):
            if ATTRIBUTE_PROTOCOL.fullmatch(function.name):
                continue
        sites.append((at.lineno, name))
    return sorted(sites)


def test_the_scan_finds_what_it_must() -> None:
    source = (
        "class A:\n"
        "    def abstract(self):\n"
        '        """Doc."""\n'
        "        raise NotImplementedError\n"
        "    def __get__(self, obj, owner=None):\n"
        "        raise AttributeError('x')\n"
        "def f(x):\n"
        "    if x:\n"
        "        raise ValueError(f'bad {x}')\n"
        "    if x is None:\n"
        "        raise KeyError\n"
        "    if x == 2:\n"
        "        raise NotImplementedError('not yet')\n"
        "    error = TypeError('stored')\n"
        "    return OSError(28, 'disk full')\n"
        "def g():\n"
        "    raise AttributeError('not the protocol')\n"
    )
    assert builtin_exception_sites(source) == [
        (9, "ValueError"),
        (11, "KeyError"),
        (13, "NotImplementedError"),
        (14, "TypeError"),
        (15, "OSError"),
        (17, "AttributeError"),
    ]


def test_library_raises_no_builtin_exception() -> None:
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for line, name in builtin_exception_sites(path.read_text()):
            found.append(f"{path.relative_to(PACKAGE.parent)}:{line}: {name}")
    assert not found, "use a class of cellcoadd/errors.py instead:\n" + "\n".join(found)


# -- readers: damaged files are format errors, programming errors are not ---------------------


@pytest.fixture(scope="module")
def coadd_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    patch = make_patch(seed=3)
    folder = tmp_path_factory.mktemp("coadds")
    return {name: api.write(patch, folder / name).read_bytes() for name in ("c.fits", "c.h5")}


@pytest.mark.parametrize("name", ["c.fits", "c.h5"])
def test_a_truncated_file_is_still_a_format_error(tmp_path, coadd_files, name) -> None:
    path = tmp_path / name
    raw = coadd_files[name]
    for cut in (len(raw) // 3, len(raw) - 2880):
        path.write_bytes(raw[:cut])
        with pytest.raises(CellCoaddFormatError) as info:
            api.read(path)
        assert info.value.path == str(path)


@pytest.mark.parametrize(
    ("name", "module", "function"),
    [
        ("c.fits", "cellcoadd.io.coadd.fits_format", "decode_metadata"),
        ("c.h5", "cellcoadd.io.coadd.hdf5_format", "decode_metadata"),
        ("c.fits", "cellcoadd.io.coadd.fits_format", "check_cell_geometry"),
        ("c.h5", "cellcoadd.io.coadd.hdf5_format", "check_cell_geometry"),
    ],
)
def test_programming_errors_in_readers_are_not_damaged_files(
    tmp_path, monkeypatch, coadd_files, name, module, function
) -> None:
    path = tmp_path / name
    path.write_bytes(coadd_files[name])

    def attribute_bug(*args: Any) -> None:
        raise AttributeError("'NoneType' object has no attribute 'skymap_config'")

    monkeypatch.setattr(f"{module}.{function}", attribute_bug)
    with pytest.raises(AttributeError, match="no attribute 'skymap_config'"):
        api.read(path)

    def takes_nothing() -> None:  # called with arguments: a TypeError in our reader's frame
        return None

    monkeypatch.setattr(f"{module}.{function}", takes_nothing)
    with pytest.raises(TypeError, match="takes 0 positional arguments") as info:
        api.read(path)
    assert not isinstance(info.value, CellCoaddError)
    path.write_bytes(coadd_files[name])  # the damaged-file path still works afterwards
    monkeypatch.undo()
    assert api.read(path).metadata.n_noise == 2


def test_which_failures_are_the_files_fault() -> None:
    def raised(action: Any) -> BaseException:
        try:
            action()
        except Exception as err:
            return err
        raise AssertionError("nothing was raised")

    # raised inside a library (json's own code): the data's fault
    assert is_file_failure(raised(lambda: json.loads(b"\xff\xfe{")))
    assert is_file_failure(raised(lambda: json.JSONDecoder().decode(5)))  # TypeError in json
    assert is_file_failure(OSError(5, "Input/output error"))
    assert is_file_failure(raised(lambda: {}["MAGZERO"]))
    assert is_file_failure(errors_module.DamagedDataError("DATASUM mismatch", hdu="IMAGE"))
    # bugs: never blamed on the file
    assert not is_file_failure(raised(lambda: None.shape))  # type: ignore[attr-defined]
    assert not is_file_failure(raised(lambda: undefined_name))  # type: ignore[name-defined]  # noqa: F821
    assert not is_file_failure(AssertionError("invariant"))
    bug = raised(lambda: Box.enclosing(5))  # a TypeError raised by cellcoadd's own code
    assert isinstance(bug, TypeError) and not is_file_failure(bug)


def test_inner_checks_keep_their_facts_in_the_format_error(tmp_path, coadd_files) -> None:
    path = tmp_path / "c.h5"
    path.write_bytes(coadd_files["c.h5"])
    with h5py.File(path, "r+") as h5:
        first = sorted(h5["cells"])[0]
        group = h5["cells"][first]
        group["image_copy"] = group["image"]  # a second hard link to the image plane
        where = group.name
    with pytest.raises(CellCoaddFormatError, match=r"unexpected objects \['image_copy'\]") as info:
        api.read(path)
    assert info.value.path == str(path)
    assert info.value.hdu == where
    assert isinstance(info.value.__cause__, errors_module.DamagedDataError)


def test_exposure_reader_lets_programming_errors_through(tmp_path, monkeypatch) -> None:
    from exposure_factory import make_exposure

    from cellcoadd.io import read_exposure, write_exposure

    path = tmp_path / "visit_12_det_34.fits"
    write_exposure(make_exposure((30.0, -5.0), shape=(48, 40), visit=12, detector=34), path)

    def attribute_bug(data: Any) -> dict[str, Any]:
        raise AttributeError("'NoneType' object has no attribute 'tobytes'")

    monkeypatch.setattr("cellcoadd.io.exposures.exposure_io._read_meta", attribute_bug)
    with pytest.raises(AttributeError, match="no attribute 'tobytes'"):
        read_exposure(path)
    monkeypatch.undo()
    assert read_exposure(path).visit == 12
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 2])  # truncated: still the file's fault
    with pytest.raises(CellCoaddFormatError) as info:
        read_exposure(path)
    assert info.value.path == str(path)


def test_a_cfitsio_failure_is_one_line_naming_the_file_once(tmp_path) -> None:
    """CFITSIO's message names the file on lines of its own, several times: the error says
    it once, on one line."""
    from cellcoadd.io import read_exposure

    path = tmp_path / "cut.fits"
    path.write_bytes(b"SIMPLE  =                    T" + b" " * 50 + b"BITPIX  = ")  # no END
    with pytest.raises(CellCoaddFormatError) as info:
        read_exposure(path)
    message = str(info.value)
    assert "\n" not in message and message.count(str(path)) == 1, message
    assert message.startswith(f"{path}: ") and "FITSIO status" in message
