"""How many visits an edge-free cell coadd rejects, and the depth it costs (paper section 5.2).

A visit *covers* a cell if any detector's imaging area overlaps the cell; it is *kept* only
if the cell lies entirely inside one detector (no detector edge or gap crosses it). The
fraction rejected is ``1 - N_kept / N_covering`` and, since the 5-sigma point-source depth
of a coadd of N equal visits grows as ``2.5 log10(sqrt(N))``, the depth lost is
``1.25 log10(N_covering / N_kept)`` mag.

The model is flat-sky: cells are squares aligned with the sky axes, placed uniformly in a
disc around a nominal field centre; each visit's focal plane is shifted by its dither offset
and rotated by its rotation angle. Everything is vectorised over cells and visits.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from cellcoadd.errors import CellCoaddValueError
from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.sim.dither import DitherPattern, RotationMode, dither_offsets, visit_rotations
from cellcoadd.sim.focal_plane import FocalPlaneConfig, lsst_focal_plane

#: Cell sides studied in the paper's Fig. 6, arcmin.
PAPER_CELL_SIZES_ARCMIN: tuple[float, ...] = (0.1, 0.5, 0.8)
#: The paper's range of rejected-visit fractions over those sizes (section 5.2).
PAPER_REJECTED_RANGE: tuple[float, float] = (0.03, 0.20)
#: LSST's 10-year r-band design number of visits (a typical sky position).
DEFAULT_N_VISITS = 184


def default_cell_size_arcmin(config: SkyMapConfig | None = None) -> float:
    """Side of cellcoadd's outer cell (inner + 2 borders), arcmin: 250 px x 0.2" = 0.833'."""
    config = config or SkyMapConfig()
    return config.cell_outer * config.pixel_scale / 60.0


def depth_loss_mag(n_covering: np.ndarray | float, n_kept: np.ndarray | float) -> np.ndarray:
    """5-sigma depth lost by keeping ``n_kept`` of ``n_covering`` equal visits, mag.

    ``1.25 log10(n_covering / n_kept)``: infinite when nothing is kept, NaN when nothing covers.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        return 1.25 * np.log10(
            np.asarray(n_covering, dtype=float) / np.asarray(n_kept, dtype=float)
        )


def classify_cells(
    focal_plane: FocalPlaneConfig,
    cell_centres: np.ndarray,
    cell_size_arcsec: float,
    visit_offsets: np.ndarray,
    visit_rotations_rad: np.ndarray,
    chunk_pairs: int = 1_000_000,
) -> tuple[np.ndarray, np.ndarray]:
    """Which visits cover each cell, and which contain it within a single detector.

    Parameters
    ----------
    focal_plane : FocalPlaneConfig
        Detector layout.
    cell_centres : ndarray, shape (n_cells, 2)
        Sky positions of the cell centres, flat-sky arcsec from the nominal field centre.
    cell_size_arcsec : float
        Side of the square cells, arcsec (sides along the sky axes).
    visit_offsets : ndarray, shape (n_visits, 2)
        Sky position of each visit's optical axis, arcsec.
    visit_rotations_rad : ndarray, shape (n_visits,)
        Rotation of each visit's focal plane on the sky, radians.
    chunk_pairs : int
        Cell-visit pairs processed at once (bounds memory).

    Returns
    -------
    covered, contained : ndarray of bool, shape (n_cells, n_visits)
        ``covered``: some detector overlaps the cell; ``contained``: one detector holds all of
        it (``contained`` implies ``covered``).
    """
    centres = np.asarray(cell_centres, dtype=float).reshape(-1, 2)
    offsets = np.asarray(visit_offsets, dtype=float).reshape(-1, 2)
    angles = np.asarray(visit_rotations_rad, dtype=float).ravel()
    if angles.size != offsets.shape[0]:
        raise CellCoaddValueError("need one rotation per visit offset")
    half = 0.5 * cell_size_arcsec
    # Candidate detectors are found at the corners of the cell's bounding box, which is
    # complete only while that box is smaller than every detector.
    max_box = 2.0 * half * float(np.max(np.abs(np.cos(angles)) + np.abs(np.sin(angles)), initial=1))
    if max_box >= focal_plane.min_detector_side_arcsec():
        raise CellCoaddValueError(
            f"cell of {cell_size_arcsec:g} arcsec is too large for detectors of "
            f"{focal_plane.min_detector_side_arcsec():g} arcsec",
            value=cell_size_arcsec,
        )
    locator = focal_plane.locator()
    det_centre = np.column_stack(
        [locator.bounds[:, :2].mean(axis=1), locator.bounds[:, 2:].mean(axis=1)]
    )
    det_half = 0.5 * np.column_stack(
        [locator.bounds[:, 1] - locator.bounds[:, 0], locator.bounds[:, 3] - locator.bounds[:, 2]]
    )
    n_cells, n_visits = centres.shape[0], offsets.shape[0]
    covered = np.zeros((n_cells, n_visits), dtype=bool)
    contained = np.zeros((n_cells, n_visits), dtype=bool)
    visits_per_chunk = max(1, chunk_pairs // max(n_cells, 1))
    signs = np.array([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]])
    for start in range(0, n_visits, visits_per_chunk):
        stop = min(start + visits_per_chunk, n_visits)
        cos, sin = np.cos(angles[start:stop]), np.sin(angles[start:stop])
        # Sky -> focal plane: p = R(-theta) (c - o); the cell's axes become u and v.
        dx = centres[:, None, 0] - offsets[None, start:stop, 0]
        dy = centres[:, None, 1] - offsets[None, start:stop, 1]
        px, py = cos * dx + sin * dy, -sin * dx + cos * dy
        ux, uy, vx, vy = cos, -sin, sin, cos
        corner_ids = np.stack(
            [
                locator.detector_at(
                    px + half * (su * ux + sv * vx), py + half * (su * uy + sv * vy)
                )
                for su, sv in signs
            ]
        )
        contained[:, start:stop] = (corner_ids[0] >= 0) & np.all(
            corner_ids == corner_ids[0], axis=0
        )
        box_half = half * (np.abs(cos) + np.abs(sin))
        hit = np.zeros(px.shape, dtype=bool)
        for sx, sy in signs:
            candidate = locator.detector_at(px + sx * box_half, py + sy * box_half)
            valid = candidate >= 0
            index = np.where(valid, candidate, 0)
            rx, ry = det_centre[index, 0] - px, det_centre[index, 1] - py
            hx, hy = det_half[index, 0], det_half[index, 1]
            # Separating-axis test on the cell's own axes (the detector axes are already
            # satisfied: the detector contains a corner of the cell's bounding box).
            along_u = np.abs(rx * ux + ry * uy) < hx * np.abs(ux) + hy * np.abs(uy) + half
            along_v = np.abs(rx * vx + ry * vy) < hx * np.abs(vx) + hy * np.abs(vy) + half
            hit |= valid & along_u & along_v
        covered[:, start:stop] = hit | contained[:, start:stop]
    return covered, contained


@dataclass(frozen=True)
class RejectionStats:
    """Per-cell visit counts for one cell size and dither pattern.

    Attributes
    ----------
    cell_size_arcmin : float
        Side of the square cells.
    dither, rotation : str
        Dither pattern and rotation mode.
    n_visits : int
        Visits simulated.
    seed : int
        Seed of the run.
    camera : str
        Focal-plane name.
    n_covering, n_kept : ndarray of int, shape (n_cells,)
        Visits overlapping each cell, and those containing it within one detector.
    """

    cell_size_arcmin: float
    dither: str
    rotation: str
    n_visits: int
    seed: int
    camera: str
    n_covering: np.ndarray
    n_kept: np.ndarray

    @property
    def fraction_rejected(self) -> np.ndarray:
        """``1 - n_kept / n_covering`` per cell (NaN for a cell no visit covers)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return 1.0 - self.n_kept / self.n_covering.astype(float)

    @property
    def depth_loss_mag(self) -> np.ndarray:
        """5-sigma depth lost per cell, mag (see :func:`depth_loss_mag`)."""
        return depth_loss_mag(self.n_covering, self.n_kept)

    def summary(self) -> dict[str, float]:
        """Mean, median, 5th and 95th percentiles of the rejected fraction and depth loss."""
        covered = self.n_covering > 0
        if not covered.any():
            nan = float("nan")
            keys = ("mean_rejected", "median_rejected", "p05_rejected", "p95_rejected")
            return {
                "cell_size_arcmin": self.cell_size_arcmin,
                "mean_n_covering": 0.0,
                **dict.fromkeys(keys, nan),
                "mean_depth_loss_mag": nan,
                "p95_depth_loss_mag": nan,
                "uncovered_cells": int(covered.size),
            }
        fraction = self.fraction_rejected[covered]
        loss = self.depth_loss_mag[covered]
        return {
            "cell_size_arcmin": self.cell_size_arcmin,
            "mean_n_covering": float(self.n_covering.mean()),
            "mean_rejected": float(fraction.mean()),
            "median_rejected": float(np.median(fraction)),
            "p05_rejected": float(np.percentile(fraction, 5)),
            "p95_rejected": float(np.percentile(fraction, 95)),
            "mean_depth_loss_mag": float(loss.mean()),
            "p95_depth_loss_mag": float(np.percentile(loss, 95)),
            "uncovered_cells": int(np.sum(~covered)),
        }

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary plus the settings (per-cell arrays omitted)."""
        settings = {k: v for k, v in asdict(self).items() if not isinstance(v, np.ndarray)}
        return {**settings, "n_cells": int(self.n_covering.size), **self.summary()}


def rejection_statistics(
    cell_size_arcmin: float,
    n_cells: int = 10_000,
    n_visits: int = DEFAULT_N_VISITS,
    dither: DitherPattern = "random",
    seed: int = 0,
    *,
    focal_plane: FocalPlaneConfig | None = None,
    rotation: RotationMode = "random",
    cell_region_radius_deg: float = 0.5,
    dither_radius_deg: float | None = None,
) -> RejectionStats:
    """Simulate edge rejection for random square cells near a field centre.

    Cell positions, dither offsets and rotations come from independent streams spawned from
    ``seed``, so runs with different cell sizes (or dither patterns) see the same cells and
    the same rotations: their differences are not noise.

    Parameters
    ----------
    cell_size_arcmin : float
        Side of the square cells, arcmin (the build's outer cell plus any kernel margin).
    n_cells : int
        Number of random cells.
    n_visits : int
        Number of visits (pointings) of the field.
    dither : "random" or "spiral"
        Dither pattern inside the hexagon (see :mod:`cellcoadd.sim.dither`).
    seed : int
        Seed of the run.
    focal_plane : FocalPlaneConfig, optional
        Detector layout, LSST-like by default.
    rotation : "random" or "none"
        Rotation of the focal plane per visit.
    cell_region_radius_deg : float
        Cells are uniform in a disc of this radius about the nominal field centre, deg.
    dither_radius_deg : float, optional
        Circumradius of the dither hexagon, deg; the focal plane's field radius by default.

    Returns
    -------
    RejectionStats
    """
    if cell_size_arcmin <= 0 or n_cells < 1 or n_visits < 1:
        raise CellCoaddValueError(
            "cell size, n_cells and n_visits must be positive",
            value=(cell_size_arcmin, n_cells, n_visits),
        )
    focal_plane = focal_plane or lsst_focal_plane()
    dither_radius = 3600.0 * (dither_radius_deg or focal_plane.field_radius_deg)
    cell_stream, dither_stream, rotation_stream = (
        np.random.default_rng(child) for child in np.random.SeedSequence(seed).spawn(3)
    )
    radius = 3600.0 * cell_region_radius_deg * np.sqrt(cell_stream.uniform(size=n_cells))
    phase = cell_stream.uniform(0.0, 2.0 * np.pi, n_cells)
    centres = np.column_stack([radius * np.cos(phase), radius * np.sin(phase)])
    offsets = dither_offsets(dither, n_visits, dither_radius, dither_stream, region="hexagon")
    angles = visit_rotations(n_visits, rotation, rotation_stream)
    covered, contained = classify_cells(
        focal_plane, centres, 60.0 * cell_size_arcmin, offsets, angles
    )
    return RejectionStats(
        cell_size_arcmin=float(cell_size_arcmin),
        dither=dither,
        rotation=rotation,
        n_visits=n_visits,
        seed=seed,
        camera=focal_plane.name,
        n_covering=covered.sum(axis=1),
        n_kept=contained.sum(axis=1),
    )


def rejection_survey(
    cell_sizes_arcmin: Sequence[float] | None = None,
    dithers: Sequence[DitherPattern] = ("random", "spiral"),
    **kwargs: Any,
) -> list[RejectionStats]:
    """:func:`rejection_statistics` for every cell size and dither pattern.

    ``cell_sizes_arcmin`` defaults to the paper's 0.1, 0.5, 0.8 arcmin plus cellcoadd's
    default outer cell; ``kwargs`` go to :func:`rejection_statistics`.
    """
    if cell_sizes_arcmin is None:
        cell_sizes_arcmin = (*PAPER_CELL_SIZES_ARCMIN, default_cell_size_arcmin())
    return [
        rejection_statistics(size, dither=dither, **kwargs)
        for dither in dithers
        for size in cell_sizes_arcmin
    ]


def rejection_table(results: Sequence[RejectionStats]) -> str:
    """Fixed-width table of the rejected fraction and depth loss, with the paper's range."""
    low, high = PAPER_REJECTED_RANGE
    sizes = ", ".join(f"{s:g}" for s in PAPER_CELL_SIZES_ARCMIN)
    lines = [
        f"paper (section 5.2, LSST OpSim r band): {100 * low:.0f}% to {100 * high:.0f}% of "
        f"visits rejected for cells of {sizes} arcmin",
        f"{'cell[arcmin]':>12} {'dither':>7} {'N_cover':>8} {'rej mean':>9} {'median':>7} "
        f"{'5-95%':>12} {'dm mean':>8} {'dm 95%':>7}",
    ]
    for stats in results:
        s = stats.summary()
        spread = f"{100 * s['p05_rejected']:.1f}-{100 * s['p95_rejected']:.1f}%"
        lines.append(
            f"{stats.cell_size_arcmin:12.3f} {stats.dither:>7} {s['mean_n_covering']:8.1f} "
            f"{100 * s['mean_rejected']:8.1f}% {100 * s['median_rejected']:6.1f}% {spread:>12} "
            f"{s['mean_depth_loss_mag']:8.3f} {s['p95_depth_loss_mag']:7.3f}"
        )
    if results:
        first = results[0]
        lines.append(
            f"({first.camera} focal plane, {first.n_visits} visits, rotation {first.rotation}, "
            f"{first.n_covering.size} cells, seed {first.seed}; dm = 5-sigma depth loss, mag)"
        )
    return "\n".join(lines)
