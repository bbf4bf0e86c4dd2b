"""A cell's identity record (tract, index, boxes, exact WCS) as stored in patch files, and
the shapes its planes must have."""

from __future__ import annotations

import json
from typing import Any, Protocol

from astropy.wcs import WCS

from cellcoadd.errors import DamagedDataError
from cellcoadd.geometry.box import Box
from cellcoadd.model import planes
from cellcoadd.model.patch_coadd import PatchMetadata
from cellcoadd.model.wcs_codec import wcs_from_record, wcs_to_record


class WcsRecords:
    """:func:`~cellcoadd.model.wcs_codec.wcs_to_record` of the WCSs met in one write.

    Each WCS object is described once (a cell's WCS goes into the cell index and into its
    image header), and header cards whose text was already parsed are not parsed again:
    the cells of a patch have the same WCS cards but for ``CRPIX``, and astropy's parsing
    of card values was most of the cost of describing a WCS.
    """

    def __init__(self) -> None:
        self._records: dict[int, tuple[WCS, dict[str, Any]]] = {}  # the WCS kept: ids stay
        self._card_values: dict[str, tuple[str, Any]] = {}

    def __call__(self, wcs: WCS) -> dict[str, Any]:
        known = self._records.get(id(wcs))
        if known is not None and known[0] is wcs:
            return known[1]
        record = wcs_to_record(wcs, card_values=self._card_values)
        self._records[id(wcs)] = (wcs, record)
        return record


class CellIdentity(Protocol):
    """What identifies a cell in a file: a :class:`CellCoadd`'s, or its geometry's
    (:class:`~cellcoadd.geometry.tract.Cell`)."""

    @property
    def tract(self) -> int: ...

    @property
    def index(self) -> tuple[int, int]: ...

    @property
    def inner_bbox(self) -> Box: ...

    @property
    def outer_bbox(self) -> Box: ...

    @property
    def wcs(self) -> WCS: ...


def cell_record_json(cell: CellIdentity, wcs_records: WcsRecords | None = None) -> str:
    """ASCII JSON of a cell's identity: tract, index, boxes and exact WCS.

    ``wcs_records`` describes the WCS (once per distinct WCS of a write); None: directly.
    """
    record = {
        "tract": cell.tract,
        "index": list(cell.index),
        "inner_bbox": cell.inner_bbox.model_dump(),
        "outer_bbox": cell.outer_bbox.model_dump(),
        "wcs": (wcs_records or wcs_to_record)(cell.wcs),
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


def check_cell_geometry(metadata: PatchMetadata, identity: dict[str, Any]) -> None:
    """Refuse a cell identity whose boxes disagree with the sky map's cell geometry
    (DamagedDataError): the shapes of its planes follow from them, so a forged box could make a
    reader allocate planes of any size."""
    config = metadata.skymap_config
    outer = config.cell_inner + 2 * config.cell_border
    inner_box, outer_box = identity["inner_bbox"], identity["outer_bbox"]
    if inner_box.shape != (config.cell_inner, config.cell_inner):
        raise DamagedDataError(f"inner box {inner_box} is not {config.cell_inner} pixels square")
    if outer_box.shape != (outer, outer) or outer_box.grow(-config.cell_border) != inner_box:
        raise DamagedDataError(
            f"outer box {outer_box} is not the inner box {inner_box} grown by {config.cell_border}"
        )


def expected_shapes(
    metadata: PatchMetadata, outer: Box, n_used: int = 0
) -> dict[str, tuple[int, ...]]:
    """Array shape of every plane (:data:`~cellcoadd.model.planes.PLANES`) of a cell with
    outer box ``outer`` and ``n_used`` used inputs (the planes with a layer per used input,
    :attr:`~cellcoadd.model.planes.PlaneSpec.per_input`)."""
    return {
        spec.name: spec.shape(outer.shape, metadata.n_noise, metadata.psf_size, n_used)
        for spec in planes.PLANES
    }
