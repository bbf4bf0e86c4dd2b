"""How an exposure's PSF is stored in an exposure file: its kind, META description and
optional ``PSF`` HDU array (see :mod:`cellcoadd.io.exposure_io` for the file layout).

========  ======================================================  =======================
PSFKIND   stored as                                               read back as
========  ======================================================  =======================
PROFILE   a GSObject of the whitelist: exact JSON description     the same GSObject
          (:mod:`cellcoadd.io.psf_codec`), no HDU
VARYING   a :class:`~cellcoadd.model.psf_profiles.VaryingPsf`: exact    the same VaryingPsf
          JSON description, no HDU
SAMPLED   any other GSObject: one oversampled pre-pixel stamp     an InterpolatedImage
GRID      any other callable: float64 cube (n_y_nodes,            a
          n_x_nodes, n, n) of oversampled pre-pixel stamps on a   :class:`~cellcoadd.io.
          :data:`PSF_GRID_NODES` x :data:`PSF_GRID_NODES` grid    psf_profiles.GridPsf`
IMAGE     a ``galsim.Image``: the stamp (dtype as given)          a bit-identical Image
========  ======================================================  =======================
"""

from __future__ import annotations

from typing import Any

import galsim
import numpy as np

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.io.psf_codec import can_encode, decode_psf, encode_psf
from cellcoadd.io.wcs_header import as_float
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.psf_profiles import GridPsf, VaryingPsf

#: Nodes a side of the grid a PSF callable is sampled on.
PSF_GRID_NODES = 5
#: Oversampling of the stored pre-pixel PSF stamps.
PSF_GRID_OVERSAMPLE = 4


def psf_payload(exposure: Exposure) -> tuple[str, dict[str, Any], np.ndarray | None]:
    """``(PSFKIND, META description, PSF HDU array or None)`` of the exposure's PSF.

    Any exception comes from the user's PSF model (a callable may fail in any way).
    """
    psf = exposure.psf
    if isinstance(psf, galsim.Image):
        scale = psf.scale if psf.wcs is not None and psf.wcs.isPixelScale() else None
        return "IMAGE", {"kind": "image", "scale": scale}, np.ascontiguousarray(psf.array)
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
    if isinstance(psf, GridPsf):
        grid = psf
    else:
        grid = GridPsf.sample(
            psf,
            exposure.shape,
            _typical_scale(exposure),
            n_nodes=PSF_GRID_NODES,
            oversample=PSF_GRID_OVERSAMPLE,
        )
    meta = {
        "kind": "grid",
        "scale": grid.scale,
        "x_nodes": [float(v) for v in grid.x_nodes],
        "y_nodes": [float(v) for v in grid.y_nodes],
    }
    return "GRID", meta, np.ascontiguousarray(grid.stamps, dtype=np.float64)


def _typical_scale(exposure: Exposure) -> float:
    """Pixel scale (arcsec) at the detector centre: sqrt of the pixel area."""
    ny, nx = exposure.shape
    jac = exposure.local_jacobian((nx - 1) / 2.0, (ny - 1) / 2.0)
    return float(np.sqrt(abs(np.linalg.det(jac))))


def read_psf(desc: Any, array: np.ndarray | None) -> Any:
    """The PSF described by META ``desc``, with the ``PSF`` HDU ``array`` when it has one.

    Raises
    ------
    CellCoaddFormatError
        (without a path) for an unknown kind, a description that does not match its kind,
        or a missing array.
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
            x_nodes=np.zeros(1), y_nodes=np.zeros(1), stamps=array, scale=desc.get("scale")
        )
        return grid(0.0, 0.0)
    if kind == "grid":
        x_nodes = np.array([as_float(v, "PSF node") for v in desc.get("x_nodes", [])])
        y_nodes = np.array([as_float(v, "PSF node") for v in desc.get("y_nodes", [])])
        return GridPsf(
            x_nodes=x_nodes,
            y_nodes=y_nodes,
            stamps=array,
            scale=as_float(desc.get("scale"), "PSF scale"),
        )
    raise _fail(f"unknown PSF kind {kind!r}")


def _fail(problem: str) -> CellCoaddFormatError:
    # the caller (read_exposure) fills in the path
    return CellCoaddFormatError("", problem)
