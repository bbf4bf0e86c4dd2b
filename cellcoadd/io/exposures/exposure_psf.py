"""How an exposure's PSF is stored in an exposure file: its kind, META description and
optional ``PSF`` HDU array (see :mod:`cellcoadd.io.exposures.exposure_io` for the file layout).

The kind follows the exposure's :attr:`~cellcoadd.model.exposure.Exposure.psf_model`, so a
bare form (GSObject, callable, ``galsim.Image``) and its wrapper (``GalSimPsf``,
``ImagePsf``) give the same file.

========  ======================================================  =======================
PSFKIND   stored as                                               read back as
========  ======================================================  =======================
PROFILE   a GSObject of the whitelist: exact JSON description     the same GSObject
          (:mod:`cellcoadd.io.exposures.psf_codec`), no HDU
VARYING   a :class:`~cellcoadd.model.psf_profiles.VaryingPsf`:    the same VaryingPsf
          exact JSON description, no HDU
SAMPLED   any other GSObject: one oversampled pre-pixel stamp     an InterpolatedImage
GRID      any other pre-pixel callable (``GalSimPsf``, or         a :class:`~cellcoadd.
          ``CallablePsf(includes_pixel=False)``): float64 cube    model.psf_profiles.
          (n_y_nodes, n_x_nodes, n, n) of oversampled stamps on   GridPsf` (pre-pixel)
          a :data:`PSF_GRID_NODES` x :data:`PSF_GRID_NODES` grid
PIXGRID   ``CallablePsf(includes_pixel=True)``: as GRID, the      ``CallablePsf(GridPsf,
          stamps sample the pixel-included profile (no pixel      includes_pixel=True)``
          added); META ``includes_pixel: true``
IMAGE     a ``galsim.Image`` / ``ImagePsf``: the stamp (dtype     a bit-identical Image
          as given)
PSFEX     ``PsfexPsf``: uint8 copy of the ``.psf`` file's bytes;  ``parse_psfex(bytes)``
          META ``sha256``, ``file_name``                          (parsed whole)
PIFF      ``PiffPsf``: uint8 copy of the Piff file's bytes; META  ``parse_piff(bytes,
          ``sha256``, ``file_name``, ``chipnum``, ``origin``      trusted=...)``: only
                                                                  with ``trust_psf``
========  ======================================================  =======================

A stored model file whose SHA-256 differs from the one in META is refused. A stored
model file is parsed whole when the exposure is read; a Piff model (pickled objects) is
loaded only when the reader is given ``trust_psf=True``, and refused otherwise.
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Callable
from typing import Any

import galsim
import numpy as np

from cellcoadd.errors import CellCoaddFormatError, CellCoaddTypeError, PsfError
from cellcoadd.io._fits.wcs_header import as_float
from cellcoadd.io.exposures.psf_codec import can_encode, decode_psf, encode_psf
from cellcoadd.io.exposures.psf_files import parse_piff, parse_psfex
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.psf import CallablePsf, GalSimPsf, ImagePsf, PiffPsf, PsfexPsf
from cellcoadd.model.psf_profiles import GridPsf, VaryingPsf

#: Nodes a side of the grid a PSF callable is sampled on.
PSF_GRID_NODES = 5
#: Oversampling of the stored PSF stamps.
PSF_GRID_OVERSAMPLE = 4

Payload = tuple[str, dict[str, Any], np.ndarray | None]
_SHA256 = re.compile(r"[0-9a-f]{64}")
# PsfModel.source of a file model built from bytes (cellcoadd.model.psf._FileModel)
_NO_FILE = "<bytes>"


def psf_payload(exposure: Exposure) -> Payload:
    """``(PSFKIND, META description, PSF HDU array or None)`` of the exposure's PSF.

    Raises
    ------
    TypeError
        For a PsfModel of a kind that cannot be stored (a user subclass).

    Any other exception comes from the user's PSF model (a callable may fail in any way).
    """
    model = exposure.psf_model
    if isinstance(model, (PsfexPsf, PiffPsf)):
        return _file_payload(model)
    if isinstance(model, ImagePsf):
        image = model.image
        scale = image.scale if image.wcs is not None and image.wcs.isPixelScale() else None
        return "IMAGE", {"kind": "image", "scale": scale}, np.ascontiguousarray(image.array)
    if isinstance(model, GalSimPsf):
        return _pre_pixel_payload(exposure, model.profile)
    if isinstance(model, CallablePsf):
        if not model.includes_pixel:
            return _pre_pixel_payload(exposure, model.func)
        grid = model.func if isinstance(model.func, GridPsf) else _sample(exposure, model.func)
        return "PIXGRID", _grid_meta("pixel_grid", grid, includes_pixel=True), _cube(grid)
    raise CellCoaddTypeError(f"a PSF model of type {type(model).__name__} cannot be stored")


def _pre_pixel_payload(
    exposure: Exposure, psf: galsim.GSObject | Callable[[float, float], galsim.GSObject]
) -> Payload:
    """A profile without the pixel response: a constant GSObject or a callable."""
    if isinstance(psf, galsim.GSObject):
        if can_encode(psf):
            return "PROFILE", {"kind": "profile", "profile": encode_psf(psf)}, None
        grid = GridPsf.sample(
            lambda x, y: psf,
            (1, 1),
            _typical_scale(exposure),
            n_nodes=1,
            oversample=PSF_GRID_OVERSAMPLE,
        )
        return "SAMPLED", {"kind": "sampled", "scale": grid.scale}, grid.stamps
    if isinstance(psf, VaryingPsf) and can_encode(psf):
        return "VARYING", {"kind": "varying", "profile": encode_psf(psf)}, None
    grid = psf if isinstance(psf, GridPsf) else _sample(exposure, psf)
    return "GRID", _grid_meta("grid", grid), _cube(grid)


def _sample(exposure: Exposure, func: Callable[[float, float], galsim.GSObject]) -> GridPsf:
    """``func`` drawn without adding a pixel on the node grid, oversampled."""
    return GridPsf.sample(
        func,
        exposure.shape,
        _typical_scale(exposure),
        n_nodes=PSF_GRID_NODES,
        oversample=PSF_GRID_OVERSAMPLE,
    )


def _grid_meta(kind: str, grid: GridPsf, **extra: Any) -> dict[str, Any]:
    return {
        "kind": kind,
        **extra,
        "scale": float(grid.scale),
        "x_nodes": [float(v) for v in grid.x_nodes],
        "y_nodes": [float(v) for v in grid.y_nodes],
    }


def _cube(grid: GridPsf) -> np.ndarray:
    return np.ascontiguousarray(grid.stamps, dtype=np.float64)


def _file_payload(model: PsfexPsf | PiffPsf) -> Payload:
    """A copy of the model file's bytes, with its SHA-256 and name."""
    if not model.data:
        raise PsfError(f"{model.source}: the PSF model file is empty")
    meta: dict[str, Any] = {
        "kind": "psfex" if isinstance(model, PsfexPsf) else "piff",
        "sha256": hashlib.sha256(model.data).hexdigest(),
        "file_name": None if model.source == _NO_FILE else os.path.basename(model.source),
        "n_bytes": len(model.data),
    }
    if isinstance(model, PiffPsf):
        meta["chipnum"] = None if model.chipnum is None else int(model.chipnum)
        meta["origin"] = int(model.origin)
    return meta["kind"].upper(), meta, np.frombuffer(model.data, dtype=np.uint8)


def _typical_scale(exposure: Exposure) -> float:
    """Pixel scale (arcsec) at the detector centre: sqrt of the pixel area."""
    ny, nx = exposure.shape
    jac = exposure.local_jacobian((nx - 1) / 2.0, (ny - 1) / 2.0)
    return float(np.sqrt(abs(np.linalg.det(jac))))


def read_psf(desc: Any, array: np.ndarray | None, *, trusted: bool = False) -> Any:
    """The PSF described by META ``desc``, with the ``PSF`` HDU ``array`` when it has one.

    A stored Piff model is loaded only when ``trusted`` (it holds pickled objects).

    Raises
    ------
    CellCoaddFormatError
        (without a path) for an unknown kind, a description that does not match its kind,
        a missing array, or a stored model file whose SHA-256 differs from META's.
    """
    if not isinstance(desc, dict):
        raise _fail("META psf must be an object")
    kind = desc.get("kind")
    if kind in ("profile", "varying"):
        psf = decode_psf(desc.get("profile"))
        expected = VaryingPsf if kind == "varying" else galsim.GSObject
        if not isinstance(psf, expected):
            raise _fail(f"PSF description does not match its kind {kind!r}")
        return psf
    if array is None:
        raise _fail(f"missing HDU PSF for a PSF of kind {kind!r}")
    if kind == "image":
        scale = desc.get("scale")
        if scale is None:
            return galsim.Image(array)
        return galsim.Image(array, scale=as_float(scale, "PSF scale"))
    if kind == "sampled":
        grid = GridPsf(
            x_nodes=np.zeros(1),
            y_nodes=np.zeros(1),
            stamps=array,
            scale=as_float(desc.get("scale"), "PSF scale"),
        )
        return grid(0.0, 0.0)
    if kind == "grid":
        return _read_grid(desc, array)
    if kind == "pixel_grid":
        if desc.get("includes_pixel") is not True:
            raise _fail("a PSF of kind 'pixel_grid' must have includes_pixel true")
        return CallablePsf(_read_grid(desc, array), includes_pixel=True)
    if kind in ("psfex", "piff"):
        return _read_file_model(kind, desc, array, trusted)
    raise _fail(f"unknown PSF kind {kind!r}")


def _read_grid(desc: dict[str, Any], array: np.ndarray) -> GridPsf:
    x_nodes = np.array([as_float(v, "PSF node") for v in desc.get("x_nodes", [])])
    y_nodes = np.array([as_float(v, "PSF node") for v in desc.get("y_nodes", [])])
    return GridPsf(
        x_nodes=x_nodes,
        y_nodes=y_nodes,
        stamps=array,
        scale=as_float(desc.get("scale"), "PSF scale"),
    )


def _read_file_model(
    kind: str, desc: dict[str, Any], array: np.ndarray, trusted: bool
) -> PsfexPsf | PiffPsf:
    """The stored copy of a PSFEx or Piff model file, checked against its SHA-256."""
    name = desc.get("file_name")
    expected = desc.get("sha256")
    if name is not None and not isinstance(name, str):
        raise _fail("META psf file_name must be a string or null")
    if not (isinstance(expected, str) and _SHA256.fullmatch(expected)):
        raise _fail("META psf sha256 must be 64 lower-case hexadecimal digits")
    if array.dtype != np.uint8 or array.ndim != 1:
        raise _fail(f"HDU PSF must hold the {kind} model file as a 1-D byte array")
    data = array.tobytes()
    actual = hashlib.sha256(data).hexdigest()
    label = f"{kind} model file {name!r}" if name else f"{kind} model file"
    if actual != expected:
        raise _fail(
            f"HDU PSF: the stored copy of the {label} is damaged or altered: its SHA-256 is "
            f"{actual}, META records {expected}"
        )
    # the model names its file, as the original did (and is stored again under that name)
    source = name if name else _NO_FILE
    try:
        if kind == "psfex":
            return parse_psfex(data, source)
        chipnum, origin = desc.get("chipnum"), desc.get("origin")
        if chipnum is not None and (isinstance(chipnum, bool) or not isinstance(chipnum, int)):
            raise _fail("META psf chipnum must be an integer or null")
        if isinstance(origin, bool) or not isinstance(origin, int) or origin not in (0, 1):
            raise _fail("META psf origin must be 0 or 1")
        return parse_piff(data, source, trusted=trusted, chipnum=chipnum, origin=origin)
    except CellCoaddFormatError as err:
        if not err.path:
            raise
        raise _fail(f"HDU PSF: the stored {label}: {err.problem}") from None


def _fail(problem: str) -> CellCoaddFormatError:
    # the caller (read_exposure) fills in the path
    return CellCoaddFormatError("", problem)
