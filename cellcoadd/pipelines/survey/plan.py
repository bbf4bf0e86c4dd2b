"""Planning a survey run: which tracts the index touches, and for each tract and band the
patches its inputs may touch, with the index rows (and their checksums) of each patch's
inputs and whether their files are still the ones indexed.

Planning reads only the index (no input file is opened, one ``stat`` per input file), so
it runs anywhere: in the client for one tract, as one task per tract on the cluster for
a survey. :func:`candidate_tracts` finds the tracts from the index's HEALPix key without
reading any row: the footprints' pixels at a coarse resolution against each tract's
circumscribed circle (exact: a tract is a candidate when a footprint pixel may reach its
box grown by the patch border); :func:`plan_tract` then assigns each input to the
patches whose outer box its footprint, projected on the tract, overlaps.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import hpgeom
import numpy as np

from cellcoadd.geometry.footprint import (
    angular_distance,
    box_corners,
    circle_pixels,
    in_ra_dec_box,
    parent_pixels,
    quads_covering_boxes,
)
from cellcoadd.geometry.skymap import SkyMap
from cellcoadd.geometry.tract import Patch, Tract
from cellcoadd.io.exposures.index import ExposureIndex, IndexedExposure
from cellcoadd.pipelines.survey.records import InputStamp, PatchKey

Region = tuple[float, float, float, float]


@dataclass(frozen=True)
class PatchPlan:
    """One patch of one band to build, and its candidate inputs (visit, detector order)."""

    key: PatchKey
    patch: Patch
    inputs: tuple[InputStamp, ...]
    #: each input's footprint on the tract: ``(4, 2)`` corners ``(x, y)``, tract pixels
    footprints: tuple[np.ndarray, ...] = field(default=(), repr=False, compare=False)
    #: why an input is no longer the file indexed (changed, vanished), one line each
    changed: tuple[str, ...] = ()

    @property
    def index(self) -> tuple[int, int]:
        return self.patch.index

    @property
    def rows(self) -> tuple[int, ...]:
        return tuple(item.row for item in self.inputs)

    def cell_costs(self) -> dict[tuple[int, int], float]:
        """The relative cost of building each cell: 1 plus the number of inputs whose
        footprint covers the cell's outer box (those the cell may accept; an input that
        only grazes it is rejected early and costs little).

        The cost of a build is in its cell x input pairs, and they vary across a patch
        (its band beside a neighbouring detector can hold twice those of the far band):
        this is what cuts a patch into parts of equal cost. About 0.15 s for 484 cells
        and 800 inputs.
        """
        cells = self.patch.cells
        count = quads_covering_boxes(self.footprints, [cell.outer_bbox for cell in cells])
        return {cell.index: 1.0 + n for cell, n in zip(cells, count, strict=True)}


@dataclass(frozen=True)
class TractPlan:
    """The patches of one tract and band that inputs may touch (or that were asked for)."""

    tract: Tract
    band: str
    patches: tuple[PatchPlan, ...]


def _grown_box_corners(tract: Tract) -> tuple[np.ndarray, np.ndarray]:
    """Tract pixel corners of the tract's box grown by a patch's outer reach."""
    config = tract.config
    return box_corners(tract.bbox, config.cell_outer * (config.patch_border_cells + 1))


def _patch_in_region(tract: Tract, patch: Patch, region: Region) -> bool:
    """Whether the patch's inner region meets ``region`` (tested on its corners, edge
    midpoints and centre, and the region's corners inside the patch)."""
    x, y = box_corners(patch.inner_bbox)
    xs = np.concatenate([x, (x + np.roll(x, -1)) / 2, [x.mean()]])
    ys = np.concatenate([y, (y + np.roll(y, -1)) / 2, [y.mean()]])
    ra, dec = tract.pixel_to_sky(xs, ys)
    if np.any(in_ra_dec_box(ra, dec, region)):
        return True
    ra0, ra1, dec0, dec1 = region
    rx, ry = tract.sky_to_pixel(np.array([ra0, ra1, ra1, ra0]), np.array([dec0, dec0, dec1, dec1]))
    box = patch.inner_bbox
    ok = np.isfinite(rx) & np.isfinite(ry)
    return bool(
        np.any(
            ok
            & (rx >= box.x_start - 0.5)
            & (rx < box.x_stop - 0.5)
            & (ry >= box.y_start - 0.5)
            & (ry < box.y_stop - 0.5)
        )
    )


def plan_tract(
    index: ExposureIndex,
    skymap: SkyMap,
    tract_id: int,
    bands: Sequence[str] | None = None,
    patches: Sequence[tuple[int, int]] | None = None,
    region: Region | None = None,
) -> list[TractPlan]:
    """The patches of tract ``tract_id`` that inputs may touch, one plan per band.

    An input may touch a patch when its footprint (the corners of its valid box, pushed
    outward, projected on the tract) overlaps the patch's outer box: the inputs of each
    patch are a superset of those its cells accept (the builder selects exactly).

    Parameters
    ----------
    bands : sequence of str, optional
        Only these bands (default: every band whose inputs touch the tract). A band
        given here is planned even without inputs when ``patches`` are given.
    patches : sequence of (int, int), optional
        Only these patches (each planned for every band, with or without inputs).
    region : (ra0, ra1, dec0, dec1), optional
        Only patches whose inner region meets this RA/Dec box (deg; RA may wrap).

    Raises
    ------
    CellCoaddIndexError
        For a tract or patch outside the sky map (names them).
    IndexRowError
        When an index row does not match its checksum (names the file and the fields).
    """
    tract = skymap[tract_id]
    wanted = None if patches is None else {(int(p[0]), int(p[1])) for p in patches}
    if wanted is not None:
        for px, py in wanted:
            tract.patch(px, py)  # IndexError naming the tract for a patch outside it
    x, y = _grown_box_corners(tract)
    ra, dec = tract.pixel_to_sky(x, y)
    rows = index.query(np.column_stack([ra, dec]))
    if bands is not None:
        wanted_bands = set(bands)
        rows = [row for row in rows if row.band in wanted_bands]
    changed: dict[int, str] = {}
    for row in rows:  # one stat per file: a done patch of a changed input is never current
        error = row.not_as_indexed(index.path)
        if error is not None:
            changed[row.id] = str(error)
    assigned: dict[tuple[str, int, int], list[tuple[IndexedExposure, np.ndarray]]] = {}
    config = tract.config
    side = config.patch_inner
    n = config.patches_per_tract
    reach = config.cell_inner * config.patch_border_cells + config.cell_border
    for row in rows:
        x, y = tract.sky_to_pixel(row.corners[:, 0], row.corners[:, 1])
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            continue  # 90 deg or more from the tract's tangent point
        footprint = np.column_stack([x, y])  # shared by every patch it may touch
        # patches whose outer box (inner box + reach) overlaps the footprint's bounding box
        lo_x = int(np.floor((x.min() + 0.5 - reach) / side))
        hi_x = int(np.floor((x.max() + 0.5 + reach) / side))
        lo_y = int(np.floor((y.min() + 0.5 - reach) / side))
        hi_y = int(np.floor((y.max() + 0.5 + reach) / side))
        for py in range(max(lo_y, 0), min(hi_y, n - 1) + 1):
            for px in range(max(lo_x, 0), min(hi_x, n - 1) + 1):
                if wanted is None or (px, py) in wanted:
                    assigned.setdefault((row.band, px, py), []).append((row, footprint))
    planned_bands = sorted(
        set(bands) if bands is not None and wanted is not None else {k[0] for k in assigned}
    )
    plans = []
    for band in planned_bands:
        keys = (
            sorted(wanted, key=lambda k: (k[1], k[0]))
            if wanted is not None
            else sorted((k[1:] for k in assigned if k[0] == band), key=lambda k: (k[1], k[0]))
        )
        items = []
        for px, py in keys:
            patch = tract.patch(px, py)
            if region is not None and not _patch_in_region(tract, patch, region):
                continue
            members = assigned.get((band, px, py), [])
            items.append(
                PatchPlan(
                    key=PatchKey(band, tract_id, px, py),
                    patch=patch,
                    inputs=tuple(
                        InputStamp(
                            row=row.id,
                            checksum=row.checksum,
                            path=row.path,
                            size=row.files[0].size,
                            mtime_ns=row.files[0].mtime_ns,
                        )
                        for row, _ in members
                    ),
                    footprints=tuple(quad for _, quad in members),
                    changed=tuple(changed[row.id] for row, _ in members if row.id in changed),
                )
            )
        if items:
            plans.append(TractPlan(tract=tract, band=band, patches=tuple(items)))
    return plans


def plan_tract_task(
    index_path: str,
    skymap: SkyMap,
    tract_id: int,
    bands: tuple[str, ...] | None,
    patches: tuple[tuple[int, int], ...] | None,
    region: Region | None,
) -> list[TractPlan]:
    """:func:`plan_tract` on a worker: opens the index read-only itself."""
    with ExposureIndex(index_path, readonly=True) as index:
        return plan_tract(index, skymap, tract_id, bands, patches, region)


def candidate_tracts(
    index: ExposureIndex,
    skymap: SkyMap,
    bands: Sequence[str] | None = None,
    region: Region | None = None,
) -> list[int]:
    """The tracts whose patches inputs of ``bands`` may touch (a superset; planning is
    exact), found from the index's HEALPix key without reading any row.

    Each tract's box grown by a patch's outer reach lies inside a circle around its
    centre; a footprint that may touch the tract has a HEALPix pixel inside that circle,
    and so does that pixel's parent at a coarse resolution (about a quarter of a tract):
    the candidates are the tracts whose circle touches a coarse parent of the footprints'
    pixels. With ``region``, only tracts whose circle meets the region's box.
    """
    pixels = index.footprint_pixels(bands)
    if len(pixels) == 0 or len(skymap) == 0:
        return []
    config = skymap.config
    size_deg = config.tract_size_deg
    coarse = index.nside
    while coarse > 1 and hpgeom.nside_to_resolution(coarse // 2) < size_deg / 4:
        coarse //= 2
    present = set(parent_pixels(pixels, index.nside, coarse).tolist())
    found = []
    for tract in skymap:
        x, y = _grown_box_corners(tract)
        ra, dec = tract.pixel_to_sky(x, y)
        cx, cy = tract.pixel_to_sky(
            (tract.bbox.x_start + tract.bbox.x_stop - 1) / 2,
            (tract.bbox.y_start + tract.bbox.y_stop - 1) / 2,
        )
        radius = float(np.max(angular_distance(float(cx[0]), float(cy[0]), ra, dec))) * 1.01
        if region is not None and not _circle_meets_region(
            float(cx[0]), float(cy[0]), radius, region
        ):
            continue
        if present.intersection(circle_pixels(coarse, float(cx[0]), float(cy[0]), radius).tolist()):
            found.append(tract.id)
    return found


def _circle_meets_region(ra: float, dec: float, radius: float, region: Region) -> bool:
    """Whether a circle (deg) may meet an RA/Dec box: the box grown by the radius (in RA
    by the radius over cos(dec) at the circle's most polar point) holds the centre."""
    ra0, ra1, dec0, dec1 = region
    polar = min(89.9, max(abs(dec) + radius, 0.0))
    grow_ra = radius / max(np.cos(np.radians(polar)), 1e-3)
    if grow_ra >= 180.0:
        return dec1 + radius >= dec >= dec0 - radius
    grown = (
        np.mod(ra0 - grow_ra, 360.0),
        np.mod(ra1 + grow_ra, 360.0),
        dec0 - radius,
        dec1 + radius,
    )
    if np.mod(ra1 - ra0, 360.0) + 2 * grow_ra >= 360.0 or (ra0 == 0.0 and ra1 == 360.0):
        grown = (0.0, 360.0, grown[2], grown[3])
    return bool(in_ra_dec_box(np.array([ra]), np.array([dec]), grown)[0])
