"""Conversion of patch coadds to and from `lsst-images <https://pypi.org/project/lsst-images/>`_.

Two forms (see ``docs/format.md``, section "lsst-images"):

* ``mode="stitched"``: one :class:`lsst.images.cells.CellCoadd`, Rubin's meaning of a cell
  coadd: the *inner* regions of the patch's inner cells on one grid (the area of
  :meth:`~cellcoadd.model.patch_coadd.PatchCoadd.stitch`), cells that are missing or empty
  marked missing in the cell PSF's bounds. The cells' borders are not kept, so
  :func:`from_lsst_images` gives back cells whose outer-border pixels are NaN with the
  ``NO_DATA`` mask bit set.
* ``mode="per_cell"``: a dict ``{(cx, cy): lsst.images.cells.CellCoadd}``, one coadd per
  cell covering its *outer* box (a one-cell grid), so nothing is lost: pixels, noise
  realizations, mask, mfrac, PSF, inputs (rejected ones too), WCS and identity come back
  bit for bit.

Mask planes carry Rubin's lsst-images names (``SAT`` is ``SATURATED``, ``CR``
``COSMIC_RAY``, ``INTRP`` ``INTERPOLATED``, ``EDGE`` ``SENSOR_EDGE``; see
:mod:`cellcoadd.io.foreign.mask_planes`), at our bit numbers, and come back under ours.

What lsst-images has no place for travels in its native metadata under ``cellcoadd.*``
keys (patch metadata, cell identity, the exact WCS, every input record, the original
units string). The image unit is always exported as ``nJy`` or as counts (``ct``, with
the zero point in ``cellcoadd.zero_point``), never as a scaled unit: lsst-images 30.x
writes a scaled unit it cannot read back.

File names: lsst-images picks its layout from the suffix, and its ``.h5`` is a Starlink
NDF file, not cellcoadd's HDF5 layout. Write lsst-images files as ``.fits`` or ``.sdf``;
:func:`from_lsst_images` refuses ``.h5``/``.hdf5`` names and cellcoadd's own files.

lsst-images needs Python >= 3.12: install the ``lsst`` extra (``pip install
'cellcoadd[lsst]'``). It is imported only when these functions run.
"""

from __future__ import annotations

import json
import math
import os
import re
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
from astropy import units as u
from astropy.wcs import WCS

from cellcoadd.errors import (
    CellCoaddFormatError,
    CellCoaddIncompatibleValuesError,
    CellCoaddTypeError,
    CellCoaddValueError,
    InvalidCoaddError,
    MissingDependencyError,
)
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.skymap import SkyMap, is_known_skymap, known_skymap_names
from cellcoadd.geometry.tract import Patch
from cellcoadd.geometry.wcs_utils import shifted_wcs
from cellcoadd.io._files.path_gate import gate_read
from cellcoadd.io.foreign.cell_coadds_layout import shape_from_quadrupole
from cellcoadd.io.foreign.mask_planes import from_rubin, rubin_description, to_rubin
from cellcoadd.model.aperture_corrections import ApertureCorrections, CellApertureCorrection
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.inputs import FLOAT_FIELDS, InputRecord
from cellcoadd.model.maskbits import MAX_BITS, MaskBits
from cellcoadd.model.observations import Observations, VisitInfo
from cellcoadd.model.patch_coadd import PatchCoadd, PatchMetadata
from cellcoadd.model.stitched import CELL_EDGE, cell_edge_mask
from cellcoadd.model.wcs_codec import wcs_from_record, wcs_to_record

Mode = Literal["stitched", "per_cell"]

#: The pip requirement that brings lsst-images in.
EXTRA_HINT = "pip install 'cellcoadd[lsst]' (lsst-images needs Python >= 3.12)"

#: Name given to the sky map in lsst-images' TractFrame.
SKYMAP_NAME = "cellcoadd"

#: Instrument name written in the provenance tables (inputs carry no instrument).
INSTRUMENT = "unknown"

#: Key of the mask-fraction image (``CellCoadd.mfrac``) in ``mask_fractions``.
MFRAC_KEY = "mfrac"

#: Metadata keys (native metadata of the lsst-images object).
KEY_FORMAT = "cellcoadd.format"
KEY_MODE = "cellcoadd.mode"
KEY_PATCH = "cellcoadd.patch_metadata"
_KEY_UNITS = "cellcoadd.units"
_KEY_ZERO_POINT = "cellcoadd.zero_point"
KEY_TRACT_WCS = "cellcoadd.tract_wcs"
KEY_CELL_WCS = "cellcoadd.cell_wcs"
KEY_CELL = "cellcoadd.cell_index"
KEY_INNER = "cellcoadd.inner_bbox"
KEY_INPUTS = "cellcoadd.inputs"
#: Width of the ``CELL_EDGE`` plane added on export (absent without it).
KEY_CELL_EDGES = "cellcoadd.cell_edges"
_KEY_MFRAC = "cellcoadd.mfrac"

#: Version of the ``cellcoadd.*`` metadata layout.
LSST_IMAGES_FORMAT = 1

_CELL_EDGE_DESCRIPTION = (
    "Outermost pixels of a cell's inner region, where the coadd (and its PSF) changes from "
    "one cell to the next."
)

_MFRAC_DESCRIPTION = (
    "Fraction of the coadd weight that came from masked (interpolated) input pixels, "
    "cellcoadd's mfrac plane."
)

#: "counts at zero point 30 ..." (the free text of PatchMetadata.units before format 1.2).
_COUNTS_AT_ZP = re.compile(r"^\s*counts?\s+at\s+(?:the\s+)?zero\s*point\s+([-+0-9.eE]+)", re.I)

LSST_SUFFIXES = (".fits", ".sdf", ".json")


def lsst_images_module() -> Any:
    """``lsst.images`` with its ``cells`` subpackage, or ImportError naming the extra."""
    try:
        import lsst.images as images
        import lsst.images.cells  # noqa: F401  (attribute of ``images`` from here on)
    except ImportError as err:
        raise MissingDependencyError(
            f"converting to or from lsst-images needs the 'lsst-images' package: {EXTRA_HINT}"
            f" ({err})",
            package="lsst.images",
        ) from err
    return images


# ----------------------------------------------------------------------------------------
# units


def export_unit(meta: PatchMetadata) -> tuple[u.UnitBase, float | None]:
    """``(unit, zero_point)`` written to lsst-images: nJy, or counts with their zero point.

    Read from ``meta.units`` at run time (``"nJy"`` or ``"count"``, with
    ``meta.zero_point`` for counts); the free text of older metadata (``"counts at zero
    point 30"``) and other spellings astropy parses are accepted. Never a scaled unit:
    lsst-images does not read back the rounded scale factors it writes.
    """
    text = meta.units
    legacy = _COUNTS_AT_ZP.match(text)
    if legacy:
        return u.ct, float(legacy.group(1))
    try:
        unit = u.Unit(text, parse_strict="raise")
    except ValueError as err:
        raise CellCoaddValueError(
            f"patch units {text!r} are not an astropy unit: {err}", value=text
        ) from None
    if unit == u.ct:
        zero_point = getattr(meta, "zero_point", None)
        if zero_point is None:
            zero_point = meta.build_config.zero_point
        return u.ct, float(zero_point)
    if unit == u.nJy:
        return u.nJy, None
    raise CellCoaddValueError(
        f"patch units {text!r}: only nJy and counts (with a zero point) are exported to lsst-images"
    )


# ----------------------------------------------------------------------------------------
# metadata codecs (lsst-images metadata values are scalars: JSON goes in strings)


def _float_bits(value: float) -> str:
    return struct.pack("<d", value).hex()


def _bits_float(text: str) -> float:
    return float(struct.unpack("<d", bytes.fromhex(text))[0])


def records_to_json(records: list[InputRecord]) -> list[dict[str, Any]]:
    # floats as IEEE-754 bytes, so NaN payloads and -0.0 come back bit for bit
    out = []
    for record in records:
        item: dict[str, Any] = record.model_dump(mode="json", exclude=set(FLOAT_FIELDS))
        item.update({name: _float_bits(getattr(record, name)) for name in FLOAT_FIELDS})
        out.append(item)
    return out


def records_from_json(items: list[dict[str, Any]]) -> list[InputRecord]:
    records = []
    for item in items:
        fields = dict(item)
        for name in FLOAT_FIELDS:
            if name in fields:  # psf_flux_outside is absent from exports before format 1.3
                fields[name] = _bits_float(fields[name])
        records.append(InputRecord.model_validate(fields))
    return records


def box_to_json(box: Box) -> list[int]:
    return [box.x_start, box.x_stop, box.y_start, box.y_stop]


def box_from_json(values: list[int]) -> Box:
    x_start, x_stop, y_start, y_stop = (int(v) for v in values)
    return Box(x_start=x_start, x_stop=x_stop, y_start=y_start, y_stop=y_stop)


# ----------------------------------------------------------------------------------------
# lsst-images building blocks


def lsst_box(images: Any, box: Box) -> Any:
    return images.Box.factory[box.y_start : box.y_stop, box.x_start : box.x_stop]


def _plane_names(bits: MaskBits) -> dict[str, str]:
    """Our mask-bit name -> lsst-images plane name (Rubin's: ``SAT`` is ``SATURATED``...)."""
    rubin = to_rubin(bits.bits, "lsst_images")
    by_bit = {bit: name for name, bit in rubin.items()}
    return {name: by_bit[bit] for name, bit in bits.bits.items()}


def mask_schema(images: Any, bits: MaskBits, *, cell_edges: bool = False) -> Any:
    # plane at overall index b = our bit b, so the bit layout is ours; names are Rubin's
    names = _plane_names(bits)
    planes: list[Any] = [None] * (max(bits.bits.values()) + 1)
    for name, bit in bits.bits.items():
        planes[bit] = images.MaskPlane(names[name], rubin_description(name))
    if cell_edges:
        if CELL_EDGE in names.values():
            raise CellCoaddValueError(f"the coadd already has a mask plane named {CELL_EDGE}")
        planes.append(images.MaskPlane(CELL_EDGE, _CELL_EDGE_DESCRIPTION))
    return images.MaskSchema(planes)


def to_lsst_mask(images: Any, mask: np.ndarray, schema: Any, bits: MaskBits, bbox: Any) -> Any:
    out = images.Mask(0, schema=schema, bbox=bbox)
    for name, bit in bits.bits.items():
        out.set(_plane_names(bits)[name], (mask >> bit) & 1 != 0)
    return out


def from_lsst_mask(mask: Any, bits: MaskBits, *, derived: tuple[str, ...] = ()) -> np.ndarray:
    """Our int32 mask from lsst-images planes named as :func:`mask_schema` names ``bits``
    (the planes ``derived`` from the others, e.g. ``CELL_EDGE``, left out)."""
    ours = {plane: name for name, plane in _plane_names(bits).items()}
    names = [plane for plane in mask.schema.names if plane not in derived]
    unknown = sorted(set(names) - set(ours))
    if unknown:
        raise InvalidCoaddError(f"lsst-images mask planes {unknown} have no cellcoadd bit")
    out = np.zeros(mask.array.shape[:2], dtype=np.int32)
    for plane in names:
        out |= mask.get(plane).astype(np.int32) << bits.bits[ours[plane]]
    return out


def _aperture_correction_fields(
    images: Any, meta: PatchMetadata, bounds: Any, shape: tuple[int, ...], first: tuple[int, int]
) -> dict[str, Any] | None:
    """lsst-images ``aperture_corrections`` (one ``CellField`` per algorithm, NaN where a
    cell has none) of the cells of ``bounds``' subgrid: ``shape`` (rows, columns) from the
    cell ``first`` = (cy, cx)."""
    corrections = meta.aperture_corrections
    if corrections is None:
        return None
    fields = {}
    for k, name in enumerate(corrections.algorithms):
        array = np.full(shape, np.nan, dtype=np.float64)
        for cell in corrections.cells:
            i, j = cell.index[1] - first[0], cell.index[0] - first[1]
            value = cell.values[k]
            if 0 <= i < shape[0] and 0 <= j < shape[1] and value is not None:
                array[i, j] = value
        fields[name] = images.cells.CellField(bounds, array)
    return fields


def lsst_image(images: Any, array: np.ndarray, bbox: Any, unit: u.UnitBase | None) -> Any:
    return images.Image(np.array(array, copy=True), bbox=bbox, unit=unit)


def _psf_moments_pix2(record: InputRecord, scale: float) -> tuple[float, float, float, bool]:
    """``(Ixx, Iyy, Ixy, flag)`` in pixel^2 from ``psf_T`` (arcsec^2) and the distortions."""
    half = record.psf_T / scale**2 / 2.0
    values = (half * (1.0 + record.psf_e1), half * (1.0 - record.psf_e1), half * record.psf_e2)
    ok = all(math.isfinite(v) for v in values)
    return (*values, not ok) if ok else (math.nan, math.nan, math.nan, True)


def input_provenance(
    images: Any,
    used: list[tuple[tuple[int, int], Box, list[InputRecord]]],
    scale: float,
    observations: Observations | None = None,
) -> Any:
    """CoaddProvenance of the used inputs: ``used`` = [(cell ij, outer box, records)].

    Instrument, physical filter and ``day_obs`` come from ``observations`` when known
    (a Rubin coadd read in); otherwise ``"unknown"``, the band and 0.
    """
    instrument = observations.instrument if observations else INSTRUMENT
    contributions_rows = [(ij, r) for ij, _, records in used for r in records if r.is_used]
    if not contributions_rows:
        return None
    provenance_type = images.cells.CoaddProvenance
    # one input row per (visit, detector): its polygon is the box holding the outer boxes
    # of the cells that used it (edge-free inputs cover each of them entirely)
    extent: dict[tuple[int, int], list[int]] = {}
    filters: dict[tuple[int, int], str] = {}
    for _, box, records in used:
        for record in records:
            if not record.is_used:
                continue
            bounds = extent.setdefault(
                record.key, [box.x_start, box.x_stop, box.y_start, box.y_stop]
            )
            bounds[0] = min(bounds[0], box.x_start)
            bounds[1] = max(bounds[1], box.x_stop)
            bounds[2] = min(bounds[2], box.y_start)
            bounds[3] = max(bounds[3], box.y_stop)
            filters.setdefault(record.key, record.band)
    inputs = provenance_type.make_empty_input_table(len(extent))
    for n, (key, (x0, x1, y0, y1)) in enumerate(sorted(extent.items())):
        info = observations.visit(key[0]) if observations else None
        inputs["instrument"][n] = instrument
        inputs["visit"][n] = key[0]
        inputs["detector"][n] = key[1]
        inputs["physical_filter"][n] = info.physical_filter if info else filters[key]
        inputs["day_obs"][n] = info.day_obs if info else 0
        inputs["polygon"][n] = images.Polygon.from_box(images.Box.factory[y0:y1, x0:x1])
    table = provenance_type.make_empty_contribution_table(len(contributions_rows))
    for n, ((i, j), record) in enumerate(contributions_rows):
        xx, yy, xy, flag = _psf_moments_pix2(record, scale)
        table["cell_i"][n] = i
        table["cell_j"][n] = j
        table["instrument"][n] = instrument
        table["visit"][n] = record.visit
        table["detector"][n] = record.detector
        table["overlaps_center"][n] = True
        table["overlap_fraction"][n] = record.overlap_fraction
        table["unmasked_fraction"][n] = math.nan  # not recorded per input by cellcoadd
        table["weight"][n] = record.weight
        table["psf_shape_xx"][n] = xx
        table["psf_shape_yy"][n] = yy
        table["psf_shape_xy"][n] = xy
        table["psf_shape_flag"][n] = flag
    return provenance_type(inputs=inputs, contributions=table)


def patch_tract_wcs(patch: PatchCoadd) -> WCS:
    """The tract WCS (array pixel (0, 0) = tract pixel (0, 0)) from a stored cell's WCS."""
    for cell in patch.cells.values():
        return shifted_wcs(cell.wcs, -cell.outer_bbox.x_start, -cell.outer_bbox.y_start)
    return patch.metadata.geometry.tract.wcs


def tract_sky_projection(images: Any, meta: PatchMetadata, tract_wcs: WCS) -> Any:
    side = meta.skymap_config.tract_pixels
    tract_box = images.Box.factory[0:side, 0:side]
    name = meta.skymap_config.name or SKYMAP_NAME
    frame = images.TractFrame(skymap=name, tract=meta.tract, bbox=tract_box)
    return images.SkyProjection.from_fits_wcs(tract_wcs, frame, pixel_bounds=tract_box)


def lsst_patch_definition(images: Any, meta: PatchMetadata, grid: Any) -> Any:
    px, py = meta.patch
    return images.cells.PatchDefinition(
        id=py * meta.skymap_config.patches_per_tract + px,
        index=images.YX(y=py, x=px),
        inner_bbox=lsst_box(images, meta.patch_inner_bbox),
        cells=grid,
    )


def common_metadata(meta: PatchMetadata, mode: Mode, zero_point: float | None) -> dict[str, Any]:
    out: dict[str, Any] = {
        KEY_FORMAT: LSST_IMAGES_FORMAT,
        KEY_MODE: mode,
        KEY_PATCH: meta.model_dump_json(),
        _KEY_UNITS: meta.units,
        _KEY_MFRAC: _MFRAC_DESCRIPTION,
    }
    if zero_point is not None:
        out[_KEY_ZERO_POINT] = zero_point
    return out


# ----------------------------------------------------------------------------------------
# export


def to_lsst_images(patch: PatchCoadd, mode: Mode = "stitched", *, cell_edges: int = 0) -> Any:
    """Convert a patch coadd to lsst-images.

    Parameters
    ----------
    patch : PatchCoadd
        The patch to convert.
    mode : {"stitched", "per_cell"}
        ``"stitched"``: one ``lsst.images.cells.CellCoadd`` of the inner regions of the
        inner cells (missing and empty cells marked missing). ``"per_cell"``: a dict
        ``{(cx, cy): lsst.images.cells.CellCoadd}``, each covering one cell's outer box,
        lossless.
    cell_edges : int
        ``"stitched"`` only: with a positive width, pixels, a ``CELL_EDGE`` mask plane
        (the next bit after ours) flags that many outermost pixels of every cell's inner
        box, as Rubin's ``StitchedCoadd.set_cell_edges`` does; :func:`from_lsst_images`
        drops it again. 0: no such plane.

    Returns
    -------
    lsst.images.cells.CellCoadd or dict

    Raises
    ------
    ImportError
        If lsst-images is not installed (see the ``lsst`` extra).
    ValueError
        For an unknown mode, or units that cannot be exported (a scaled non-flux unit).

    Examples
    --------
    >>> coadd = to_lsst_images(patch)              # doctest: +SKIP
    >>> coadd.write("patch.fits")  # never a .h5 name  # doctest: +SKIP
    """
    if not isinstance(patch, PatchCoadd):
        raise CellCoaddTypeError(
            f"patch must be a PatchCoadd, got {type(patch).__name__}", allowed=PatchCoadd
        )
    if mode not in ("stitched", "per_cell"):
        raise CellCoaddValueError(
            f"mode must be 'stitched' or 'per_cell', got {mode!r}",
            value=mode,
            allowed=("stitched", "per_cell"),
        )
    if isinstance(cell_edges, bool) or not isinstance(cell_edges, int) or cell_edges < 0:
        raise CellCoaddValueError(
            f"cell_edges must be a width in pixels (0: none), got {cell_edges!r}",
            value=cell_edges,
        )
    if cell_edges and mode != "stitched":
        raise CellCoaddIncompatibleValuesError(
            "cell_edges applies to mode='stitched' (per-cell coadds have no cell edges inside)",
            values={"mode": mode, "cell_edges": cell_edges},
        )
    images = lsst_images_module()
    if mode == "stitched":
        return _to_stitched(images, patch, cell_edges)
    return {index: _to_single_cell(images, patch, cell) for index, cell in patch.cells.items()}


def _to_stitched(images: Any, patch: PatchCoadd, cell_edges: int = 0) -> Any:
    meta = patch.metadata
    unit, zero_point = export_unit(meta)
    side = meta.cell_inner
    all_cells = meta.all_cell_indices
    cx0 = min(c[0] for c in all_cells)
    cy0 = min(c[1] for c in all_cells)
    n_x = max(c[0] for c in all_cells) - cx0 + 1
    n_y = max(c[1] for c in all_cells) - cy0 + 1
    cells_api = images.cells
    grid_box = images.Box.factory[cy0 * side : (cy0 + n_y) * side, cx0 * side : (cx0 + n_x) * side]
    grid = cells_api.CellGrid(bbox=grid_box, cell_shape=images.YX(y=side, x=side))
    inner = meta.patch_inner_bbox
    bbox = lsst_box(images, inner)

    def ij(index: tuple[int, int]) -> tuple[int, int]:
        return (index[1] - cy0, index[0] - cx0)

    missing = set()
    inner_indices = meta.inner_cell_indices
    i_min = min(ij(c)[0] for c in inner_indices)
    j_min = min(ij(c)[1] for c in inner_indices)
    n_i = max(ij(c)[0] for c in inner_indices) - i_min + 1
    n_j = max(ij(c)[1] for c in inner_indices) - j_min + 1
    psf = np.full((n_i, n_j, meta.psf_size, meta.psf_size), np.nan, dtype=np.float64)
    used: list[tuple[tuple[int, int], Box, list[InputRecord]]] = []
    inputs_json: dict[str, Any] = {}
    for index in inner_indices:
        i, j = ij(index)
        cell = patch.cells.get(index)
        if cell is not None:
            inputs_json[f"{index[0]},{index[1]}"] = records_to_json(cell.inputs)
        if cell is None or cell.is_empty:
            missing.add(cells_api.CellIJ(i=i, j=j))
            continue
        psf[i - i_min, j - j_min] = cell.psf
        used.append(((i, j), cell.outer_bbox, cell.inputs))
    bounds = cells_api.CellGridBounds(grid=grid, bbox=bbox, missing=frozenset(missing))
    tract_wcs = patch_tract_wcs(patch)
    projection = tract_sky_projection(images, meta, tract_wcs)
    schema = mask_schema(images, meta.mask_bits, cell_edges=bool(cell_edges))
    provenance = input_provenance(images, used, meta.skymap_config.pixel_scale, meta.observations)
    mask = to_lsst_mask(images, patch.stitch("mask"), schema, meta.mask_bits, bbox)
    if cell_edges:
        mask.set(CELL_EDGE, cell_edge_mask(patch, inner, cell_edges))
    coadd = cells_api.CellCoadd(
        lsst_image(images, patch.stitch("image"), bbox, unit),
        mask=mask,
        variance=lsst_image(images, patch.stitch("variance"), bbox, unit**2),
        mask_fractions={MFRAC_KEY: lsst_image(images, patch.stitch("mfrac"), bbox, None)},
        noise_realizations=[
            lsst_image(images, patch.stitch("noise", k), bbox, unit) for k in range(meta.n_noise)
        ],
        sky_projection=projection,
        band=meta.band,
        psf=cells_api.CellPointSpreadFunction(psf, bounds),
        patch=lsst_patch_definition(images, meta, grid),
        provenance=provenance,
        aperture_corrections=_aperture_correction_fields(
            images, meta, bounds, psf.shape[:2], (i_min + cy0, j_min + cx0)
        ),
    )
    coadd.metadata.update(common_metadata(meta, "stitched", zero_point))
    if cell_edges:
        coadd.metadata[KEY_CELL_EDGES] = cell_edges
    coadd.metadata[KEY_TRACT_WCS] = json.dumps(wcs_to_record(tract_wcs))
    coadd.metadata[KEY_INPUTS] = json.dumps(inputs_json)
    return coadd


def _to_single_cell(images: Any, patch: PatchCoadd, cell: CellCoadd) -> Any:
    meta = patch.metadata
    unit, zero_point = export_unit(meta)
    cells_api = images.cells
    outer = cell.outer_bbox
    bbox = lsst_box(images, outer)
    # a one-cell grid whose cell is the outer box, so the borders are kept
    grid = cells_api.CellGrid(bbox=bbox, cell_shape=images.YX(y=outer.ny, x=outer.nx))
    missing = frozenset({cells_api.CellIJ(i=0, j=0)}) if cell.is_empty else frozenset()
    bounds = cells_api.CellGridBounds(grid=grid, bbox=bbox, missing=missing)
    tract_wcs = shifted_wcs(cell.wcs, -outer.x_start, -outer.y_start)
    schema = mask_schema(images, meta.mask_bits)
    provenance = input_provenance(
        images, [((0, 0), outer, cell.inputs)], meta.skymap_config.pixel_scale, meta.observations
    )
    coadd = cells_api.CellCoadd(
        lsst_image(images, cell.image, bbox, unit),
        mask=to_lsst_mask(images, cell.mask, schema, meta.mask_bits, bbox),
        variance=lsst_image(images, cell.variance, bbox, unit**2),
        mask_fractions={MFRAC_KEY: lsst_image(images, cell.mfrac, bbox, None)},
        noise_realizations=[lsst_image(images, plane, bbox, unit) for plane in cell.noise],
        sky_projection=tract_sky_projection(images, meta, tract_wcs),
        band=meta.band,
        psf=cells_api.CellPointSpreadFunction(cell.psf[np.newaxis, np.newaxis].copy(), bounds),
        patch=lsst_patch_definition(images, meta, grid),
        provenance=provenance,
    )
    coadd.metadata.update(common_metadata(meta, "per_cell", zero_point))
    coadd.metadata[KEY_CELL] = json.dumps([cell.index[0], cell.index[1], cell.tract])
    coadd.metadata[KEY_INNER] = json.dumps(box_to_json(cell.inner_bbox))
    coadd.metadata[KEY_CELL_WCS] = json.dumps(wcs_to_record(cell.wcs))
    coadd.metadata[KEY_INPUTS] = json.dumps(records_to_json(cell.inputs))
    return coadd


# ----------------------------------------------------------------------------------------
# import


def from_lsst_images(obj: Any) -> PatchCoadd:
    """Convert lsst-images coadds written by :func:`to_lsst_images` back to a PatchCoadd.

    Parameters
    ----------
    obj : lsst.images.cells.CellCoadd, mapping of them, or path
        A stitched coadd, one per-cell coadd, a mapping ``{(cx, cy): coadd}`` of per-cell
        coadds of one patch, or the path of a file lsst-images wrote (``.fits``, ``.sdf``,
        ``.json``; read with its reader, which needs ``requests``).

    Returns
    -------
    PatchCoadd
        Per-cell input: the cells exactly. Stitched input: the inner cells that had data,
        their inner regions exact and their outer borders NaN with ``NO_DATA`` set; cells
        marked missing that had inputs come back empty.

        A coadd made by Rubin's pipelines (no ``cellcoadd.*`` metadata): the geometry is
        that of the sky map it names (``SkyMap.named``: ``lsst_cells_v1``...), checked
        against its WCS and cell grid; every cell of the patch whose inner box it covers
        and whose PSF it has, as for stitched input; the used inputs from its provenance
        (their zero points unknown: NaN), the instrument and visits, the aperture
        corrections, mask planes under our names. What it does not say is recorded as
        unknown: ``mfrac`` NaN without a ``mfrac`` mask fraction, ``software_version``
        ``"unknown (Rubin lsst-images coadd)"``.

    Raises
    ------
    ImportError
        If lsst-images is not installed.
    InvalidCoaddError
        If the coadds mix patches, or a coadd made by Rubin's pipelines (no
        ``cellcoadd.*`` metadata) is not on a named cell sky map cellcoadd knows, has
        no patch definition, is not in nJy or disagrees with its sky map.
    CellCoaddFormatError
        If a path is a cellcoadd file, a ``.h5``/``.hdf5`` name or not an lsst-images name.
    """
    images = lsst_images_module()
    if isinstance(obj, (str, os.PathLike)):
        obj = _read_path(images, Path(obj))
    if isinstance(obj, Mapping):
        coadds = list(obj.values())
        if not coadds:
            raise InvalidCoaddError("no lsst-images coadd to convert")
        return _from_per_cell(coadds)
    if not isinstance(obj, images.cells.CellCoadd):
        raise CellCoaddTypeError(
            f"expected an lsst.images.cells.CellCoadd, a mapping of them or a path, "
            f"got {type(obj).__name__}"
        )
    if obj.metadata.get(KEY_FORMAT) is None:
        return _from_rubin(images, obj)  # made by Rubin's pipelines
    mode = _metadata_of(obj)[KEY_MODE]
    if mode == "per_cell":
        return _from_per_cell([obj])
    return _from_stitched(obj)


def _read_path(images: Any, path: Path) -> Any:
    name = path.name.lower()
    if name.endswith((".h5", ".hdf5")):
        raise CellCoaddFormatError(
            path,
            ".h5/.hdf5 names belong to cellcoadd's HDF5 layout (read them with "
            "cellcoadd.read); lsst-images would take them for Starlink NDF. Write lsst-images "
            "files as .fits or .sdf",
        )
    if not name.endswith(LSST_SUFFIXES):
        raise CellCoaddFormatError(path, f"lsst-images files end in {', '.join(LSST_SUFFIXES)}")
    gate_read(path, what="lsst-images file")  # a regular file, symlinks resolved
    if name.endswith(".fits") and _is_cellcoadd_fits(path):
        raise CellCoaddFormatError(
            path, "a cellcoadd FITS file, not an lsst-images one: read it with cellcoadd.read"
        )
    from lsst.images.serialization import read_archive

    return read_archive(path)


def _is_cellcoadd_fits(path: Path) -> bool:
    from astropy.io import fits

    try:
        with fits.open(path) as hdus:
            header = hdus[0].header
            return "CCFORMAT" in header
    except OSError:
        return False


def _metadata_of(coadd: Any) -> Mapping[str, Any]:
    metadata = coadd.metadata
    if metadata.get(KEY_FORMAT) is None:
        raise InvalidCoaddError(
            "this lsst-images coadd was not written by cellcoadd (no 'cellcoadd.format' "
            "metadata); only coadds from to_lsst_images can be converted back"
        )
    version = metadata[KEY_FORMAT]
    if version != LSST_IMAGES_FORMAT:
        raise InvalidCoaddError(
            f"cellcoadd lsst-images metadata version {version} is not supported "
            f"(this cellcoadd reads version {LSST_IMAGES_FORMAT})"
        )
    if metadata.get(KEY_MODE) not in ("stitched", "per_cell"):
        raise InvalidCoaddError(f"unknown cellcoadd.mode {metadata.get(KEY_MODE)!r}")
    return metadata


def _patch_metadata(coadd: Any) -> PatchMetadata:
    meta = PatchMetadata.model_validate_json(str(_metadata_of(coadd)[KEY_PATCH]))
    unit, _ = export_unit(meta)
    if coadd.unit != unit:
        raise InvalidCoaddError(
            f"the lsst-images coadd is in {coadd.unit}, its cellcoadd metadata say {meta.units}"
        )
    return meta


def _from_per_cell(coadds: list[Any]) -> PatchCoadd:
    meta = _patch_metadata(coadds[0])
    cells: dict[tuple[int, int], CellCoadd] = {}
    for coadd in coadds:
        metadata = _metadata_of(coadd)
        if metadata[KEY_MODE] != "per_cell":
            raise InvalidCoaddError("a mapping of coadds must hold per-cell coadds only")
        if _patch_metadata(coadd) != meta:
            raise InvalidCoaddError("the per-cell coadds belong to different patches")
        cell = _cell_from_single(coadd, meta)
        if cell.index in cells:
            raise InvalidCoaddError(f"cell {cell.index} is given twice")
        cells[cell.index] = cell
    return PatchCoadd(meta, cells)


def _float32(image: Any) -> np.ndarray:
    return np.asarray(image.array, dtype=np.float32)


def _cell_from_single(coadd: Any, meta: PatchMetadata) -> CellCoadd:
    metadata = coadd.metadata
    cx, cy, tract = json.loads(str(metadata[KEY_CELL]))
    inner = box_from_json(json.loads(str(metadata[KEY_INNER])))
    outer = Box(
        x_start=coadd.bbox.x.start,
        x_stop=coadd.bbox.x.stop,
        y_start=coadd.bbox.y.start,
        y_stop=coadd.bbox.y.stop,
    )
    psf = np.asarray(coadd.psf._array[0, 0], dtype=np.float64)
    return CellCoadd(
        image=_float32(coadd.image),
        mask=from_lsst_mask(coadd.mask, meta.mask_bits),
        variance=_float32(coadd.variance),
        noise=_noise(coadd, outer.shape),
        mfrac=_float32(coadd.mask_fractions[MFRAC_KEY]),
        psf=psf,
        inputs=records_from_json(json.loads(str(metadata[KEY_INPUTS]))),
        tract=int(tract),
        index=(int(cx), int(cy)),
        inner_bbox=inner,
        outer_bbox=outer,
        wcs=wcs_from_record(json.loads(str(metadata[KEY_CELL_WCS]))),
    )


def _noise(coadd: Any, shape: tuple[int, int]) -> np.ndarray:
    planes = [_float32(plane) for plane in coadd.noise_realizations]
    if not planes:
        return np.zeros((0, *shape), dtype=np.float32)
    return np.stack(planes)


def _from_stitched(coadd: Any) -> PatchCoadd:
    meta = _patch_metadata(coadd)
    metadata = coadd.metadata
    inner_box = meta.patch_inner_bbox
    if (coadd.bbox.x.start, coadd.bbox.y.start) != (inner_box.x_start, inner_box.y_start) or (
        tuple(coadd.bbox.shape) != inner_box.shape
    ):
        raise InvalidCoaddError(
            f"stitched coadd covers {coadd.bbox}, not the patch inner box {inner_box}"
        )
    tract_wcs = wcs_from_record(json.loads(str(metadata[KEY_TRACT_WCS])))
    inputs = {
        tuple(int(v) for v in key.split(",")): records_from_json(items)
        for key, items in json.loads(str(metadata[KEY_INPUTS])).items()
    }
    image = _float32(coadd.image)
    variance = _float32(coadd.variance)
    mfrac = _float32(coadd.mask_fractions[MFRAC_KEY])
    derived = (CELL_EDGE,) if metadata.get(KEY_CELL_EDGES) else ()
    mask = from_lsst_mask(coadd.mask, meta.mask_bits, derived=derived)
    noise = _noise(coadd, image.shape)
    no_data = meta.mask_bits.value("NO_DATA")
    bounds = coadd.psf.bounds
    cells_api = lsst_images_module().cells
    grid_x0, grid_y0 = bounds.grid.bbox.x.start, bounds.grid.bbox.y.start
    side = meta.cell_inner
    cells: dict[tuple[int, int], CellCoadd] = {}
    for index in meta.inner_cell_indices:
        if index not in inputs:
            continue  # the cell was not in the patch
        records = inputs[index]
        inner, outer = meta.cell_boxes(index)
        wcs = shifted_wcs(tract_wcs, outer.x_start, outer.y_start)
        ij = cells_api.CellIJ(
            i=(index[1] * side - grid_y0) // side, j=(index[0] * side - grid_x0) // side
        )
        if not bounds.contains_cell(ij):
            cells[index] = CellCoadd.empty(
                tract=meta.tract,
                index=index,
                inner_bbox=inner,
                outer_bbox=outer,
                wcs=wcs,
                n_noise=meta.n_noise,
                psf_size=meta.psf_size,
                inputs=records,
                mask_bits=meta.mask_bits,
            )
            continue
        cells[index] = CellCoadd(
            image=_embed(image, inner_box, inner, outer, np.nan),
            mask=_embed(mask, inner_box, inner, outer, no_data),
            variance=_embed(variance, inner_box, inner, outer, np.nan),
            noise=_embed(noise, inner_box, inner, outer, np.nan),
            mfrac=_embed(mfrac, inner_box, inner, outer, np.nan),
            psf=np.asarray(coadd.psf[ij].array, dtype=np.float64),
            inputs=records,
            tract=meta.tract,
            index=index,
            inner_bbox=inner,
            outer_bbox=outer,
            wcs=wcs,
        )
    return PatchCoadd(meta, cells)


def _embed(stitched: np.ndarray, patch_box: Box, inner: Box, outer: Box, fill: float) -> np.ndarray:
    """A cell's outer-box plane: its inner box cut from ``stitched``, ``fill`` elsewhere."""
    src_rows, src_cols = inner.slices_in(patch_box)
    dst_rows, dst_cols = inner.slices_in(outer)
    out = np.full((*stitched.shape[:-2], *outer.shape), fill, dtype=stitched.dtype)
    out[..., dst_rows, dst_cols] = stitched[..., src_rows, src_cols]
    return out


# ----------------------------------------------------------------------------------------
# coadds made by Rubin's pipelines

#: ``software_version`` recorded for a coadd made by Rubin (lsst-images does not say which).
RUBIN_SOFTWARE = "unknown (Rubin lsst-images coadd)"
#: Largest disagreement, pixels, between a Rubin coadd's sky projection and its named sky
#: map's tract WCS at the corners of the coadd's box.
WCS_TOLERANCE = 1e-3


def _rubin_geometry(coadd: Any) -> tuple[Patch, str]:
    """The sky-map patch of a Rubin coadd, from the sky map it names, checked against its
    patch definition, cell grid and sky projection."""
    name = coadd.skymap
    if name is None or not is_known_skymap(str(name)):
        raise InvalidCoaddError(
            f"this lsst-images coadd has no cellcoadd metadata (made by Rubin's pipelines?) "
            f"and is on sky map {name!r}, which cellcoadd does not know by name "
            f"({', '.join(known_skymap_names())}): its geometry cannot be derived",
            value=name,
        )
    skymap = SkyMap.named(str(name))
    config = skymap.config
    definition = coadd.patch
    if definition is None:
        raise InvalidCoaddError("this lsst-images coadd has no patch definition")
    tract_id = int(coadd.tract)
    patch = skymap.patch_from_rubin_id(tract_id, int(definition.id))
    index = (int(definition.index.x), int(definition.index.y))
    if index != patch.index:
        raise InvalidCoaddError(
            f"patch id {definition.id} is patch {patch.index} of {name}, but the coadd's "
            f"patch index is {index}",
            value=index,
        )
    grid = coadd.psf.bounds.grid
    side = config.cell_inner
    shape = (int(grid.cell_shape.y), int(grid.cell_shape.x))
    if shape != (side, side) or grid.bbox.x.start % side or grid.bbox.y.start % side:
        raise InvalidCoaddError(
            f"the coadd's cells are {shape} px from ({grid.bbox.x.start}, "
            f"{grid.bbox.y.start}); {name} has {side}-px cells from the tract origin",
            value=shape,
        )
    box = coadd.bbox
    xs = np.array([box.x.start, box.x.stop - 1, box.x.start, box.x.stop - 1], dtype=float)
    ys = np.array([box.y.start, box.y.start, box.y.stop - 1, box.y.stop - 1], dtype=float)
    sky = coadd.sky_projection.pixel_to_sky(x=xs, y=ys)
    tract = patch.tract
    x, y = tract.sky_to_pixel(np.asarray(sky.ra.deg), np.asarray(sky.dec.deg))
    off = float(np.max(np.hypot(x - xs, y - ys)))
    if not off <= WCS_TOLERANCE:
        raise InvalidCoaddError(
            f"the coadd's sky projection disagrees with {name} tract {tract_id}: the corners "
            f"of its box are {off:.4g} px from where the sky map puts them",
            value=off,
        )
    return patch, str(name)


def _rubin_mask_bits(schema: Any) -> tuple[MaskBits, dict[str, str]]:
    """Our mask bits for an lsst-images mask schema (plane position = bit) and the
    lsst-images plane name of each of our names."""
    rubin = {plane.name: bit for bit, plane in enumerate(schema) if plane is not None}
    too_high = sorted(name for name, bit in rubin.items() if bit >= MAX_BITS)
    if too_high:
        raise InvalidCoaddError(
            f"mask planes {too_high} are at bits beyond cellcoadd's 0..{MAX_BITS - 1}",
            value=too_high,
        )
    ours = from_rubin(rubin, "lsst_images")
    by_bit = {bit: name for name, bit in rubin.items()}
    planes = {name: by_bit[bit] for name, bit in ours.items()}
    if "NO_DATA" not in ours:
        ours["NO_DATA"] = min(set(range(MAX_BITS)) - set(ours.values()))
    return MaskBits(bits=ours), planes


def _rubin_inputs(
    coadd: Any, first: tuple[int, int], band: str, scale: float
) -> tuple[dict[tuple[int, int], list[InputRecord]], Observations | None]:
    """Used inputs of each cell (tract-global index) and the observations, from the
    coadd's provenance."""
    provenance = coadd.provenance
    if provenance is None:
        return {}, None
    inputs: dict[tuple[int, int], list[InputRecord]] = {}
    for row in provenance.contributions:
        index = (first[0] + int(row["cell_j"]), first[1] + int(row["cell_i"]))
        shape = shape_from_quadrupole(
            float(row["psf_shape_xx"]),
            float(row["psf_shape_yy"]),
            float(row["psf_shape_xy"]),
            bool(row["psf_shape_flag"]),
            scale,
        )
        inputs.setdefault(index, []).append(
            InputRecord(
                visit=int(row["visit"]),
                detector=int(row["detector"]),
                band=band,
                weight=float(row["weight"]),
                status="used",
                overlap_fraction=float(row["overlap_fraction"]),
                zero_point=math.nan,  # not recorded
                **shape,
            )
        )
    table = provenance.inputs
    instruments = {str(name) for name in table["instrument"]}
    if len(instruments) != 1:
        return inputs, None
    visits: dict[int, VisitInfo] = {}
    for row in table:
        visits.setdefault(
            int(row["visit"]),
            VisitInfo(
                visit=int(row["visit"]),
                physical_filter=str(row["physical_filter"]),
                day_obs=int(row["day_obs"]),
            ),
        )
    return inputs, Observations(instrument=instruments.pop(), visits=tuple(visits.values()))


def _rubin_aperture_corrections(
    coadd: Any, cells: list[tuple[tuple[int, int], Any]]
) -> ApertureCorrections | None:
    fields = dict(coadd.aperture_corrections or {})
    if not fields:
        return None
    algorithms = tuple(sorted(fields))
    rows = []
    for index, ij in cells:
        values = []
        for name in algorithms:
            value = float(fields[name].value_in_cell(ij))
            values.append(value if math.isfinite(value) else None)
        if any(v is not None for v in values):
            rows.append(CellApertureCorrection(index=index, values=tuple(values)))
    return ApertureCorrections(algorithms=algorithms, cells=tuple(rows))


def _from_rubin(images: Any, coadd: Any) -> PatchCoadd:
    """A PatchCoadd of a stitched coadd made by Rubin's pipelines (see
    :func:`from_lsst_images`)."""
    geometry, name = _rubin_geometry(coadd)
    if coadd.unit != u.nJy:
        raise InvalidCoaddError(
            f"this lsst-images coadd is in {coadd.unit}: a coadd made by Rubin is read in nJy "
            "only (the zero point of other units is not recorded)",
            value=str(coadd.unit),
        )
    config = geometry.config
    bounds = coadd.psf.bounds
    side = config.cell_inner
    first = (bounds.grid.bbox.x.start // side, bounds.grid.bbox.y.start // side)
    box = coadd.bbox
    covered = Box(x_start=box.x.start, x_stop=box.x.stop, y_start=box.y.start, y_stop=box.y.stop)
    band = str(coadd.band or "")
    mask_bits, planes = _rubin_mask_bits(coadd.mask.schema)
    cells_api = images.cells
    present: list[tuple[tuple[int, int], Any]] = []
    for index in geometry.cell_indices:
        cell = geometry.tract.cell(*index)
        inside = covered.intersection(cell.inner_bbox) == cell.inner_bbox
        ij = cells_api.CellIJ(i=index[1] - first[1], j=index[0] - first[0])
        if inside and bounds.contains_cell(ij):
            present.append((index, ij))
    if not present:
        raise InvalidCoaddError("the lsst-images coadd holds no whole cell of its patch")
    psf_size = int(np.asarray(coadd.psf[present[0][1]].array).shape[0])
    scale = config.pixel_scale
    inputs, observations = _rubin_inputs(coadd, first, band, scale)
    tract = geometry.tract
    meta = PatchMetadata(
        skymap_config=config,
        tract=tract.id,
        tract_center=tract.center,
        patch=geometry.index,
        band=band,
        units="nJy",
        mask_bits=mask_bits,
        build_config=BuildConfig(
            n_noise=len(coadd.noise_realizations), psf_size=psf_size, units="nJy"
        ),
        software_version=RUBIN_SOFTWARE,
        observations=observations,
        aperture_corrections=_rubin_aperture_corrections(coadd, present),
    )
    image, variance = _float32(coadd.image), _float32(coadd.variance)
    mask = np.zeros(image.shape, dtype=np.int32)
    for ours, plane in planes.items():
        mask |= coadd.mask.get(plane).astype(np.int32) << mask_bits.bits[ours]
    fractions = coadd.mask_fractions or {}
    mfrac = (
        _float32(fractions[MFRAC_KEY])
        if MFRAC_KEY in fractions
        else np.full(image.shape, np.nan, np.float32)
    )
    noise = _noise(coadd, image.shape)
    no_data = mask_bits.value("NO_DATA")
    wcs = tract.wcs
    cells: dict[tuple[int, int], CellCoadd] = {}
    for index, ij in present:
        inner, outer = meta.cell_boxes(index)
        if not inputs.get(index):
            raise InvalidCoaddError(
                f"cell {index} has a PSF but the coadd's provenance lists no input for it",
                value=index,
            )
        cells[index] = CellCoadd(
            image=_embed(image, covered, inner, outer, np.nan),
            mask=_embed(mask, covered, inner, outer, no_data),
            variance=_embed(variance, covered, inner, outer, np.nan),
            noise=_embed(noise, covered, inner, outer, np.nan),
            mfrac=_embed(mfrac, covered, inner, outer, np.nan),
            psf=np.asarray(coadd.psf[ij].array, dtype=np.float64),
            inputs=inputs.get(index, []),
            tract=tract.id,
            index=index,
            inner_bbox=inner,
            outer_bbox=outer,
            wcs=shifted_wcs(wcs, outer.x_start, outer.y_start),
        )
    return PatchCoadd(meta, cells)
