"""The pieces of the lsst-images conversion (:mod:`cellcoadd.io.foreign.lsst_images`): metadata
keys, units, masks, provenance and geometry, shared by the export and the import."""

from __future__ import annotations

import math
import re
import struct
from typing import Any, Literal

import numpy as np
from astropy import units as u
from astropy.wcs import WCS

from cellcoadd.errors import CellCoaddValueError, InvalidCoaddError, MissingDependencyError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.wcs_utils import shifted_wcs
from cellcoadd.model.inputs import FLOAT_FIELDS, InputRecord
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.patch_coadd import PatchCoadd, PatchMetadata

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
_KEY_MFRAC = "cellcoadd.mfrac"

#: Version of the ``cellcoadd.*`` metadata layout.
LSST_IMAGES_FORMAT = 1

#: Descriptions of cellcoadd's default mask bits (lsst-images stores one per plane).
MASK_DESCRIPTIONS: dict[str, str] = {
    "BAD": "Detector defect in an input exposure (interpolated before coaddition).",
    "SAT": "Saturated in an input exposure (interpolated before coaddition).",
    "CR": "Cosmic ray in an input exposure (interpolated before coaddition).",
    "EDGE": "Detector edge in an input exposure.",
    "NO_DATA": "No input data (empty cell, or outside the valid region).",
    "INTRP": "Interpolated over.",
    "SUSPECT": "Near saturation or non-linear in an input exposure.",
    "STREAK": "Satellite trail in an input exposure.",
}

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


def mask_schema(images: Any, bits: MaskBits) -> Any:
    # plane at overall index b = our bit b, so the bit layout is ours
    planes: list[Any] = [None] * (max(bits.bits.values()) + 1)
    for name, bit in bits.bits.items():
        description = MASK_DESCRIPTIONS.get(name, f"cellcoadd mask bit {name}.")
        planes[bit] = images.MaskPlane(name, description)
    return images.MaskSchema(planes)


def to_lsst_mask(images: Any, mask: np.ndarray, schema: Any, bits: MaskBits, bbox: Any) -> Any:
    out = images.Mask(0, schema=schema, bbox=bbox)
    for name, bit in bits.bits.items():
        out.set(name, (mask >> bit) & 1 != 0)
    return out


def from_lsst_mask(mask: Any, bits: MaskBits) -> np.ndarray:
    unknown = sorted(set(mask.schema.names) - set(bits.bits))
    if unknown:
        raise InvalidCoaddError(f"lsst-images mask planes {unknown} have no cellcoadd bit")
    out = np.zeros(mask.array.shape[:2], dtype=np.int32)
    for name in mask.schema.names:
        out |= mask.get(name).astype(np.int32) << bits.bits[name]
    return out


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
) -> Any:
    """CoaddProvenance of the used inputs: ``used`` = [(cell ij, outer box, records)]."""
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
        inputs["instrument"][n] = INSTRUMENT
        inputs["visit"][n] = key[0]
        inputs["detector"][n] = key[1]
        inputs["physical_filter"][n] = filters[key]
        inputs["day_obs"][n] = 0
        inputs["polygon"][n] = images.Polygon.from_box(images.Box.factory[y0:y1, x0:x1])
    table = provenance_type.make_empty_contribution_table(len(contributions_rows))
    for n, ((i, j), record) in enumerate(contributions_rows):
        xx, yy, xy, flag = _psf_moments_pix2(record, scale)
        table["cell_i"][n] = i
        table["cell_j"][n] = j
        table["instrument"][n] = INSTRUMENT
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
    frame = images.TractFrame(skymap=SKYMAP_NAME, tract=meta.tract, bbox=tract_box)
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
