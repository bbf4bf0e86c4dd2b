"""The FITS layout of the LSST pipelines' ``lsst.cell_coadds`` package, written with fitsio.

See ``docs/format.md`` ("LSST cell_coadds layout") for the layout as read and written.
In short: a primary HDU holding only the tract WCS; an unnamed binary table with one row
per cell (grid-local ``cell_id`` and the outer-box planes ``image``, ``mask``,
``variance``, ``psf``, ``maskfrac``, ``noise_00``...) whose header carries the grid and
identity keywords; tables ``CELL`` (the inputs used by each cell), ``VISIT``, ``MASKDEF``,
``VISIT_SUMMARY`` and ``APCORR`` (per-cell aperture corrections: every column kept from a
Rubin file, ``PatchMetadata.aperture_corrections``; without them only the cell ``x``,
``y`` columns). ``INBBOX`` is the grid box grown by the cell border, as Rubin writes it.
Every HDU has CHECKSUM/DATASUM. The cell table header also
carries ``MAGZERO`` for counts (``TUNIT2 = 'legacy'``) and ``TRACTPIX``, the tract side:
keywords the LSST writer adds for any extra metadata and its reader ignores.

What our model holds beyond that layout (the metadata JSON, every cell's exact identity
and WCS, empty cells, rejected inputs and the exact input records) goes into three extra
HDUs that the LSST reader never looks at: ``CELLCOADD`` (uint8 image, the metadata JSON,
as the ``METADATA`` HDU of our own FITS layout), ``CELLCOADD_CELLS`` (one row per cell:
index, row in the cell table or -1, identity JSON) and ``CELLCOADD_INPUTS`` (every input
record of every cell). A file without them (written by the LSST pipelines) is read from
the LSST part alone (:mod:`cellcoadd.io.foreign.cell_coadds_reader`).

This module holds the conventions shared by the writer and the reader and the writer.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import fitsio
import numpy as np
from astropy.wcs import WCS

from cellcoadd.errors import (
    CellCoaddFormatError,
    CellCoaddIncompatibleValuesError,
    CellCoaddRangeError,
)
from cellcoadd.geometry.wcs_utils import shifted_wcs
from cellcoadd.io._fits.checksums import DATACRC_PLACEHOLDER
from cellcoadd.io._fits.paths import cfitsio_path
from cellcoadd.io._fits.wcs_header import wcs_cards
from cellcoadd.io.coadd import format_version
from cellcoadd.io.coadd.cell_records import cell_record_json
from cellcoadd.io.coadd.format_version import sha256_hex
from cellcoadd.io.coadd.inputs_table import inputs_to_array
from cellcoadd.io.foreign.mask_planes import to_rubin
from cellcoadd.model.aperture_corrections import ApertureCorrections
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.inputs import InputRecord
from cellcoadd.model.observations import Observations
from cellcoadd.model.patch_coadd import PatchCoadd, PatchMetadata

#: ``VERSION`` written (the ``FILE_FORMAT_VERSION`` of lsst.cell_coadds that this follows).
LSST_VERSION = "0.8"
#: Versions read: ``MASKDEF`` and the ``CELL`` shape columns exist from 0.6; 1.0 is the
#: first major version the LSST reader itself refuses.
MIN_VERSION, MAX_VERSION = (0, 6), (1, 0)
#: Values of ``TUNIT2`` (``lsst.cell_coadds.CoaddUnits``).
LSST_UNITS = ("legacy", "nJy", "chi")
#: Keyword of the cell table holding the AB zero point of ``legacy`` (counts) pixels, which
#: lsst.cell_coadds itself does not record ("typically 27"): never assumed on reading.
ZERO_POINT_KEY = "MAGZERO"
#: Keyword of the cell table holding the tract side in pixels (for sky maps without a name).
TRACT_PIXELS_KEY = "TRACTPIX"
#: Vertices stored per overlap polygon (``POLYVERT``).
POLYGON_VERTICES = 8
#: Written as ``INSTRUME`` and ``SKYMAP`` when the coadd records neither (our own sky maps;
#: inputs of unknown instrument).
UNKNOWN_NAME = "cellcoadd"
#: Our extension HDUs (the LSST reader ignores them).
EXT_METADATA, EXT_CELLS, EXT_INPUTS = "CELLCOADD", "CELLCOADD_CELLS", "CELLCOADD_INPUTS"
#: Number of HDUs cellcoadd writes in this layout, stated in the primary header as CCNHDU.
N_HDUS = 10  # primary, cells, CELL, VISIT, MASKDEF, VISIT_SUMMARY, APCORR and our three
CCNHDU_CARD = {"name": "CCNHDU", "value": N_HDUS, "comment": "HDUs in this file (cellcoadd)"}
#: Keywords of the cell table header that identify the layout.
IDENTIFYING_KEYWORDS = ("VERSION", "GRCELL1", "GRSHAPE1", "GRMIN1", "OCELL1", "PSFSIZE1")

_BLOCK = 2880


@dataclass(frozen=True)
class CellGrid:
    """The LSST cell grid of a patch: its cells with the patch's border cells.

    ``first`` is the tract-global index of grid cell ``(0, 0)``; grid cell ``(i, j)`` is
    our cell ``(first[0] + i, first[1] + j)`` and its inner box starts at tract pixel
    ``GRMIN + (i, j) * cell_inner``.
    """

    cell_inner: int
    cell_outer: int
    shape: int
    first: tuple[int, int]

    @property
    def grid_min(self) -> tuple[int, int]:
        return (self.first[0] * self.cell_inner, self.first[1] * self.cell_inner)

    def local(self, index: tuple[int, int]) -> tuple[int, int]:
        return (index[0] - self.first[0], index[1] - self.first[1])

    def global_index(self, local: tuple[int, int]) -> tuple[int, int]:
        return (local[0] + self.first[0], local[1] + self.first[1])


def grid_of(metadata: PatchMetadata) -> CellGrid:
    """The grid of ``metadata``'s patch: inner cells plus ``patch_border_cells`` rings."""
    config = metadata.skymap_config
    border, per_patch = config.patch_border_cells, config.cells_per_patch
    px, py = metadata.patch
    return CellGrid(
        cell_inner=config.cell_inner,
        cell_outer=config.cell_outer,
        shape=per_patch + 2 * border,
        first=(px * per_patch - border, py * per_patch - border),
    )


def lsst_units(units: str) -> str:
    """``TUNIT2`` for our ``units``: ``nJy`` as such, counts (at any zero point) ``legacy``."""
    return "nJy" if units == "nJy" else "legacy"


def ascii_text(text: str) -> str:
    """``text`` for an ASCII-only FITS field (non-ASCII characters JSON-escaped)."""
    return json.dumps(text, ensure_ascii=True)[1:-1]


def quadrupole(record: InputRecord, pixel_scale: float) -> tuple[float, float, float, bool]:
    """``(ixx, iyy, ixy, flag)`` in coadd pixels^2 from a record's adaptive-moment shape.

    Our ``psf_T = Ixx + Iyy`` (arcsec^2) and ``psf_e1, psf_e2`` are distortions
    (``(Ixx - Iyy) / T``, ``2 Ixy / T``; see :class:`~cellcoadd.model.inputs.InputRecord`).
    NaN values give the flag set and zero moments.
    """
    e1, e2, size = record.psf_e1, record.psf_e2, record.psf_T
    e_sq = e1 * e1 + e2 * e2
    if not (math.isfinite(e1) and math.isfinite(e2) and math.isfinite(size)) or e_sq >= 1:
        return 0.0, 0.0, 0.0, True
    trace = size / pixel_scale**2
    return trace * (1 + e1) / 2, trace * (1 - e1) / 2, trace * e2 / 2, False


def shape_from_quadrupole(
    ixx: float, iyy: float, ixy: float, flag: bool, pixel_scale: float
) -> dict[str, float]:
    """``psf_fwhm``, ``psf_e1``, ``psf_e2``, ``psf_T`` (our conventions) from a quadrupole."""
    det = ixx * iyy - ixy * ixy
    trace = ixx + iyy
    if flag or not (math.isfinite(det) and math.isfinite(trace)) or det <= 0 or trace <= 0:
        nan = float("nan")
        return {"psf_fwhm": nan, "psf_e1": nan, "psf_e2": nan, "psf_T": nan}
    sigma = det**0.25 * pixel_scale
    return {
        "psf_fwhm": 2.0 * math.sqrt(2.0 * math.log(2.0)) * sigma,
        "psf_e1": (ixx - iyy) / trace,
        "psf_e2": 2.0 * ixy / trace,
        "psf_T": trace * pixel_scale**2,
    }


# ------------------------------------------------------------------------------ recognition


def _raw_header(stream: Any) -> dict[str, str] | None:
    """Keyword -> raw value text of the header at the stream's position (None if none)."""
    cards: dict[str, str] = {}
    for _ in range(1000):
        block = stream.read(_BLOCK)
        if len(block) != _BLOCK:
            return None
        for start in range(0, _BLOCK, 80):
            card = block[start : start + 80].decode("ascii", "replace")
            key = card[:8].strip()
            if key == "END":
                return cards
            if card[8:10] == "= ":
                cards.setdefault(key, card[10:].split("/")[0].strip().strip("'").strip())
    return None


def _data_bytes(cards: dict[str, str]) -> int:
    naxis = int(cards.get("NAXIS", "0"))
    if naxis == 0:
        return 0
    size = abs(int(cards["BITPIX"])) // 8
    for axis in range(1, naxis + 1):
        size *= int(cards[f"NAXIS{axis}"])
    size = (size + int(cards.get("PCOUNT", "0"))) * int(cards.get("GCOUNT", "1"))
    return -(-size // _BLOCK) * _BLOCK


def is_cell_coadds_file(path: str) -> bool:
    """Whether ``path`` looks like an lsst.cell_coadds FITS file (never raises).

    Reads only the first two headers: the primary must lack our ``CCFORMAT`` keyword and
    HDU 1 must be a binary table carrying the grid keywords (:data:`IDENTIFYING_KEYWORDS`).
    """
    try:
        with open(path, "rb") as stream:
            primary = _raw_header(stream)
            if primary is None or "SIMPLE" not in primary or "CCFORMAT" in primary:
                return False
            stream.seek(_data_bytes(primary), 1)
            table = _raw_header(stream)
    except (OSError, ValueError, KeyError):
        return False
    if table is None or table.get("XTENSION") != "BINTABLE":
        return False
    return all(key in table for key in IDENTIFYING_KEYWORDS)


# ------------------------------------------------------------------------------ writing


def _stored_cells(patch: PatchCoadd) -> list[CellCoadd]:
    """Cells that get a row of the cell table, in grid order (y outer, x inner).

    An empty cell is left out (LSST grids hold no cell without inputs) when it is exactly
    what :meth:`CellCoadd.empty` makes of its identity and inputs, so the reader rebuilds
    it; any other empty cell keeps a row so its planes survive.
    """
    meta = patch.metadata
    stored = []
    for cell in patch.values():
        if cell.is_empty:
            rebuilt = CellCoadd.empty(
                tract=cell.tract,
                index=cell.index,
                inner_bbox=cell.inner_bbox,
                outer_bbox=cell.outer_bbox,
                wcs=cell.wcs,
                n_noise=meta.n_noise,
                psf_size=meta.psf_size,
                inputs=cell.inputs,
                mask_bits=meta.mask_bits,
            )
            if cell.equals(rebuilt):
                continue
        stored.append(cell)
    return sorted(stored, key=lambda cell: (cell.index[1], cell.index[0]))


def _table_dtype(meta: PatchMetadata) -> np.dtype:
    side, psf = meta.cell_outer, meta.psf_size
    plane = (side, side)
    fields: list[tuple[str, str, tuple[int, ...]]] = [
        ("cell_id", ">i2", (2,)),
        ("image", ">f4", plane),
        ("mask", ">i4", plane),
        ("variance", ">f4", plane),
        ("psf", ">f8", (psf, psf)),
        ("maskfrac", ">f4", plane),
    ]
    fields += [(f"noise_{n:02}", ">f4", plane) for n in range(meta.n_noise)]
    return np.dtype(fields)


def inner_bbox_keys(grid: CellGrid) -> tuple[int, int, int, int]:
    """``INBBOX11, INBBOX12, INBBOX21, INBBOX22`` as Rubin writes them: the grid box grown by
    the cell border on every side (afw's inclusive maxima).

    lsst.cell_coadds' ``MultipleCellCoadd`` defaults its ``inner_bbox`` to the box from the
    first grid cell's bounding box to the last one's, and its grid gives the cells of the
    grid's edges their outer border: ``-200 ... 3199`` for patch (0, 0) of
    ``lsst_cells_v1`` (the patch's outer box), not the grid box ``-150 ... 3149``.
    """
    gx, gy = grid.grid_min
    border = (grid.cell_outer - grid.cell_inner) // 2
    stop = grid.shape * grid.cell_inner - 1 + border
    return gx - border, gy - border, gx + stop, gy + stop


def _header_keys(meta: PatchMetadata, grid: CellGrid) -> list[dict[str, Any]]:
    gx, gy = grid.grid_min
    box = inner_bbox_keys(grid)
    units = lsst_units(meta.units)
    observations = meta.observations
    instrument = observations.instrument if observations else UNKNOWN_NAME
    skymap = meta.skymap_config.name or UNKNOWN_NAME
    values: list[tuple[str, Any, str]] = [
        ("GRCELL1", grid.cell_inner, "inner cell size x"),
        ("GRCELL2", grid.cell_inner, "inner cell size y"),
        ("GRSHAPE1", grid.shape, "cells in the grid along x"),
        ("GRSHAPE2", grid.shape, "cells in the grid along y"),
        ("GRMIN1", gx, "tract pixel x of the inner box of grid cell 0"),
        ("GRMIN2", gy, "tract pixel y of the inner box of grid cell 0"),
        ("OCELL1", grid.cell_outer, "outer cell size x"),
        ("OCELL2", grid.cell_outer, "outer cell size y"),
        ("PSFSIZE1", meta.psf_size, "PSF image size x"),
        ("PSFSIZE2", meta.psf_size, "PSF image size y"),
        ("INBBOX11", box[0], "inner bbox min x"),
        ("INBBOX12", box[1], "inner bbox min y"),
        ("INBBOX21", box[2], "inner bbox max x (inclusive)"),
        ("INBBOX22", box[3], "inner bbox max y (inclusive)"),
        ("VERSION", LSST_VERSION, "lsst.cell_coadds file format version"),
        ("TUNIT2", units, "image units"),
        ("TUNIT4", f"{units}**2", "variance units"),
        ("INSTRUME", ascii_text(instrument), "instrument"),
        ("FILTER", ascii_text(meta.band), "band"),
        ("SKYMAP", skymap, "sky map name"),
        ("TRACT", meta.tract, "tract"),
        ("PATCH_X", meta.patch[0], "patch index x"),
        ("PATCH_Y", meta.patch[1], "patch index y"),
        ("NNOISE", meta.n_noise, "noise realizations"),
        (TRACT_PIXELS_KEY, meta.skymap_config.tract_pixels, "tract side, pixels"),
    ]
    if units == "legacy":  # counts: the zero point, which the LSST layout does not record
        values.append((ZERO_POINT_KEY, meta.zero_point, "AB zero point of the pixel values"))
    keys = [{"name": n, "value": v, "comment": c} for n, v, c in values]
    return [*keys, DATACRC_PLACEHOLDER]


def _cell_row(cell: CellCoadd, grid: CellGrid, dtype: np.dtype) -> np.ndarray:
    row = np.zeros(1, dtype=dtype)
    row["cell_id"][0] = grid.local(cell.index)
    for column, plane in (("image", "image"), ("mask", "mask"), ("variance", "variance")):
        row[column][0] = getattr(cell, plane)
    row["psf"][0] = cell.psf
    row["maskfrac"][0] = cell.mfrac
    for n in range(cell.n_noise):
        row[f"noise_{n:02}"][0] = cell.noise[n]
    return row


def _used_table(stored: list[CellCoadd], grid: CellGrid, pixel_scale: float) -> np.ndarray:
    rows = []
    for cell in stored:
        cx, cy = grid.local(cell.index)
        for record in cell.inputs:
            if record.is_used:
                ixx, iyy, ixy, flag = quadrupole(record, pixel_scale)
                rows.append(
                    (cx, cy, record.visit, record.detector, True, record.overlap_fraction)
                    + (record.weight, ixx, iyy, ixy, flag)
                )
    names = ["cell_x", "cell_y", "visit", "detector", "overlaps_center", "overlap_fraction"]
    names += ["weight", "psf_shape_ixx", "psf_shape_iyy", "psf_shape_ixy", "psf_shape_flag"]
    formats = ["<i8"] * 4 + ["?"] + ["<f8"] * 5 + ["?"]
    return np.array(rows, dtype=list(zip(names, formats, strict=True)))


def _visit_tables(
    stored: list[CellCoadd], observations: Observations | None
) -> tuple[np.ndarray, np.ndarray]:
    """``VISIT`` and ``VISIT_SUMMARY`` rows of the used inputs.

    Physical filter and ``day_obs`` come from ``observations`` where it lists the visit;
    otherwise the band and 0. The overlap polygon of an input is the box covering the outer
    boxes of the cells that used it (pixel edges, tract pixels): cellcoadd does not keep the
    exposure footprints.
    """
    filters: dict[int, str] = {}
    days: dict[int, int] = {}
    boxes: dict[tuple[int, int], list[float]] = {}
    for cell in stored:
        box = cell.outer_bbox
        edges = [box.x_start - 0.5, box.y_start - 0.5, box.x_stop - 0.5, box.y_stop - 0.5]
        for record in cell.inputs:
            if not record.is_used:
                continue
            if record.visit not in filters:
                info = observations.visit(record.visit) if observations else None
                name = info.physical_filter if info else record.band
                filters[record.visit] = ascii_text(name)
                days[record.visit] = info.day_obs if info else 0
            old = boxes.setdefault(record.key, edges)
            boxes[record.key] = [*map(min, old[:2], edges[:2]), *map(max, old[2:], edges[2:])]
    width = max([1, *(len(name) for name in filters.values())])
    visits = np.array(
        [(v, filters[v].encode(), days[v]) for v in sorted(filters)],
        dtype=[("visit", "<i8"), ("physical_filter", f"S{width}"), ("day_obs", "<i8")],
    )
    summary = np.zeros(
        len(boxes),
        dtype=[
            ("visit", "<i8"),
            ("detector", "<i2"),
            ("physical_filter", "S32"),
            ("day_obs", "<i8"),
            ("num_vertices", "<i2"),
            ("polygon_vertices", "<f4", (POLYGON_VERTICES, 2)),
        ],
    )
    for row, ((visit, detector), (x0, y0, x1, y1)) in enumerate(sorted(boxes.items())):
        if not -(2**15) <= detector < 2**15:
            raise CellCoaddRangeError(
                f"detector {detector} does not fit VISIT_SUMMARY's int16 column",
                value=detector,
                low=-(2**15),
                high=2**15 - 1,
                detector=detector,
            )
        ring = [(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]  # closed, as afw lists it
        vertices = (ring + ring)[:POLYGON_VERTICES]
        summary[row] = (visit, detector, filters[visit].encode()[:32], days[visit], 5, vertices)
    return visits, summary


def _apcorr(
    stored: list[CellCoadd], grid: CellGrid, corrections: ApertureCorrections | None
) -> np.ndarray:
    """``APCORR`` as Rubin writes it: ``x``, ``y`` (grid-local, int64) and one float64
    column per algorithm, one row per cell with a map, in the order kept (NaN where a cell
    has no value for an algorithm).

    Without aperture corrections (our own builds compute none): one row per stored cell and
    no algorithm column, so the LSST reader finds a map, empty, for every cell.
    """
    if corrections is None:
        local = [grid.local(cell.index) for cell in stored]
        return np.array(local, dtype=[("x", "<i8"), ("y", "<i8")])
    dtype = [("x", "<i8"), ("y", "<i8")] + [(name, "<f8") for name in corrections.algorithms]
    table = np.zeros(len(corrections.cells), dtype=dtype)
    for row, cell in enumerate(corrections.cells):
        values = [math.nan if value is None else value for value in cell.values]
        table[row] = (*grid.local(cell.index), *values)
    return table


def _maskdef(meta: PatchMetadata) -> np.ndarray:
    # Rubin's (afw) plane names: see cellcoadd.io.foreign.mask_planes
    bits = sorted(to_rubin(meta.mask_bits.bits, "afw").items(), key=lambda item: item[1])
    width = max([1, *(len(name) for name, _ in bits)])
    return np.array(
        [(name.encode(), bit) for name, bit in bits],
        dtype=[("MASK_NAME", f"S{width}"), ("BIT_VALUE", "<u4")],
    )


def _extension_tables(
    patch: PatchCoadd, rows: dict[tuple[int, int], int]
) -> tuple[np.ndarray, np.ndarray]:
    """``CELLCOADD_CELLS`` (index, row or -1, identity JSON) and ``CELLCOADD_INPUTS``."""
    records = [cell_record_json(cell) for cell in patch.values()]
    width = max([1, *(len(text) for text in records)])
    cells = np.zeros(
        len(records),
        dtype=[("CELL_X", "<i8"), ("CELL_Y", "<i8"), ("ROW", "<i4"), ("CELL", f"S{width}")],
    )
    for n, (index, text) in enumerate(zip(patch, records, strict=True)):
        cells[n] = (index[0], index[1], rows.get(index, -1), text.encode("ascii"))
    owners = [index for index, cell in patch.items() for _ in cell.inputs]
    table = inputs_to_array([r for cell in patch.values() for r in cell.inputs], ascii_only=True)
    inputs = np.zeros(len(table), dtype=[("CELL_X", "<i8"), ("CELL_Y", "<i8"), *table.dtype.descr])
    inputs["CELL_X"] = [index[0] for index in owners]
    inputs["CELL_Y"] = [index[1] for index in owners]
    for name in table.dtype.names or ():
        inputs[name] = table[name]
    return cells, inputs


def _tract_wcs(patch: PatchCoadd) -> WCS:
    """The WCS of tract pixels, from a cell's WCS (the sky map's if there is no cell)."""
    for cell in patch.values():
        return shifted_wcs(cell.wcs, -cell.outer_bbox.x_start, -cell.outer_bbox.y_start)
    return patch.metadata.geometry.tract.wcs


def _write_table(fits: fitsio.FITS, table: np.ndarray, extname: str, keys: list[Any]) -> None:
    fits.create_table_hdu(dtype=table.dtype, extname=extname)
    if len(table):
        fits[-1].write(table)
    fits[-1].write_keys([*keys, DATACRC_PLACEHOLDER])
    fits[-1].write_checksum()


def check_writable(patch: PatchCoadd, path: str, stored: list[CellCoadd] | None = None) -> None:
    """Refuse, naming ``path``, a patch the layout cannot hold: one without any cell with
    data (lsst.cell_coadds neither writes nor reads a patch without cells), or aperture
    corrections of cells that are not the patch's."""
    if stored is None:
        stored = _stored_cells(patch)
    if not stored:
        meta = patch.metadata
        raise CellCoaddFormatError(
            path,
            f"tract {meta.tract} patch {meta.patch} has no cell with data: the cell_coadds "
            "layout cannot hold an empty patch (its reader needs at least one cell); write "
            "it in our FITS or HDF5 format",
        )
    corrections = patch.metadata.aperture_corrections
    if corrections is not None:
        cells = set(patch.metadata.all_cell_indices)
        outside = [cell.index for cell in corrections.cells if cell.index not in cells]
        if outside:
            raise CellCoaddFormatError(
                path,
                f"aperture corrections are given for cells {outside[:5]}, which are not cells "
                f"of patch {patch.metadata.patch}",
            )


def write_cell_coadds(patch: PatchCoadd, path: str, *, compress: bool = False) -> None:
    """Write ``patch`` in the lsst.cell_coadds layout to a new file ``path`` (replaced).

    Rows of the cell table are written one at a time, so memory does not grow with the
    number of cells. :func:`cellcoadd.io.api.write` wraps this (atomic, checksums).
    """
    if compress:
        raise CellCoaddIncompatibleValuesError(
            "the cell_coadds layout has no compression; use compression='none'",
            values={"compress": compress},
        )
    meta = patch.metadata
    grid = grid_of(meta)
    stored = _stored_cells(patch)
    check_writable(patch, path, stored)
    payload, version = format_version.metadata_payload(meta)
    cards, _ = wcs_cards(_tract_wcs(patch))
    with fitsio.FITS(cfitsio_path(path), "rw", clobber=True) as fits:
        # CCNHDU: a file cut at an HDU boundary is still valid FITS; the count tells
        fits.write(None, header=[*cards, CCNHDU_CARD, DATACRC_PLACEHOLDER])
        fits[-1].write_checksum()
        dtype = _table_dtype(meta)
        units = ["", lsst_units(meta.units), "", f"{lsst_units(meta.units)}**2"]
        fits.create_table_hdu(dtype=dtype, units=units + [""] * (len(dtype.names or ()) - 4))
        table = fits[-1]
        for row, cell in enumerate(stored):
            table.write(_cell_row(cell, grid, dtype), firstrow=row)
        table.write_keys(_header_keys(meta, grid))
        table.write_checksum()
        pixel_scale = meta.skymap_config.pixel_scale
        _write_table(fits, _used_table(stored, grid, pixel_scale), "CELL", [])
        visits, summary = _visit_tables(stored, meta.observations)
        _write_table(fits, visits, "VISIT", [])
        _write_table(fits, _maskdef(meta), "MASKDEF", [])
        _write_table(fits, summary, "VISIT_SUMMARY", [{"name": "POLYVERT", "value": 8}])
        _write_table(fits, _apcorr(stored, grid, meta.aperture_corrections), "APCORR", [])
        data = np.frombuffer(payload, dtype=np.uint8)
        fits.create_image_hdu(dims=data.shape, dtype=data.dtype, extname=EXT_METADATA)
        fits[-1].write(data)
        fits[-1].write_keys(
            [
                {"name": "CCVERS", "value": version, "comment": "cellcoadd format version"},
                {"name": "METASHA", "value": sha256_hex(payload), "comment": "SHA-256"},
                DATACRC_PLACEHOLDER,
            ]
        )
        fits[-1].write_checksum()
        rows = {cell.index: row for row, cell in enumerate(stored)}
        cells, inputs = _extension_tables(patch, rows)
        _write_table(fits, cells, EXT_CELLS, [])
        _write_table(fits, inputs, EXT_INPUTS, [])
