"""A cell's identity record (tract, index, boxes, exact WCS) as stored in patch files, and
the shapes its planes must have."""

from __future__ import annotations

import json
from typing import Any

from cellcoadd.geometry.box import Box
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.patch_coadd import PatchMetadata
from cellcoadd.model.wcs_codec import wcs_from_record, wcs_to_record

#: Pixel planes of a cell (besides the inputs table).
PLANES = ("image", "mask", "variance", "mfrac", "noise", "psf")


def cell_record_json(cell: CellCoadd) -> str:
    """ASCII JSON of a cell's identity: tract, index, boxes and exact WCS."""
    record = {
        "tract": cell.tract,
        "index": list(cell.index),
        "inner_bbox": cell.inner_bbox.model_dump(),
        "outer_bbox": cell.outer_bbox.model_dump(),
        "wcs": wcs_to_record(cell.wcs),
    }
    return json.dumps(record, ensure_ascii=True, separators=(",", ":"), allow_nan=False)


def parse_cell_record(text: str | bytes) -> dict[str, Any]:
    """Inverse of :func:`cell_record_json`: tract, index, inner_bbox, outer_bbox, wcs."""
    record = json.loads(text)
    return {
        "tract": int(record["tract"]),
        "index": (int(record["index"][0]), int(record["index"][1])),
        "inner_bbox": Box.model_validate(record["inner_bbox"]),
        "outer_bbox": Box.model_validate(record["outer_bbox"]),
        "wcs": wcs_from_record(record["wcs"]),
    }


def expected_shapes(metadata: PatchMetadata, outer: Box) -> dict[str, tuple[int, ...]]:
    """Array shape of every plane of a cell with outer box ``outer``."""
    ny, nx = outer.shape
    psf = metadata.psf_size
    return {
        "image": (ny, nx),
        "mask": (ny, nx),
        "variance": (ny, nx),
        "mfrac": (ny, nx),
        "noise": (metadata.n_noise, ny, nx),
        "psf": (psf, psf),
    }
