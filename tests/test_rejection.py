"""Edge-rejection statistics of cells on a dithered focal plane (paper section 5.2)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from cellcoadd.analysis import (
    PAPER_REJECTED_RANGE,
    Detector,
    FocalPlaneConfig,
    classify_cells,
    decam_like_focal_plane,
    default_cell_size_arcmin,
    depth_loss_mag,
    hexagon_offsets,
    lsst_focal_plane,
    rejection_statistics,
    rejection_survey,
    rejection_table,
    spiral_offsets,
)
from cellcoadd.cli.analyze import analyze
from cellcoadd.plots import plot_rejection
from cellcoadd.sim.dither import in_hexagon

LSST = lsst_focal_plane()
ARCSEC_PER_MM = 20.0  # 0.2"/px over 10 micron pixels
CCD_SIDE = 4096 * 0.2  # arcsec


def _one_visit(focal_xy: tuple[float, float], size_arcsec: float, angle: float = 0.0):
    """Classify one cell centred at focal-plane ``focal_xy`` (arcsec) for one visit on axis."""
    x, y = focal_xy
    # The visit's focal plane is rotated by ``angle`` on the sky: sky = R(angle) focal.
    sky = [np.cos(angle) * x - np.sin(angle) * y, np.sin(angle) * x + np.cos(angle) * y]
    covered, contained = classify_cells(
        LSST, np.array([sky]), size_arcsec, np.zeros((1, 2)), np.array([angle])
    )
    return bool(covered[0, 0]), bool(contained[0, 0])


def test_lsst_focal_plane_geometry() -> None:
    assert len(LSST.detectors) == 189
    assert LSST.min_detector_side_arcsec() / 60 == pytest.approx(13.6533, abs=1e-3)
    assert 9.5 < LSST.imaging_area_deg2() < 10.0
    bounds = LSST.bounds_arcsec()
    assert bounds[:, 0].min() == pytest.approx(-2.5 * 127.0 * ARCSEC_PER_MM + 0.5 * 1.54 * 20, 0.01)
    locator = LSST.locator()
    centres = np.column_stack([bounds[:, :2].mean(axis=1), bounds[:, 2:].mean(axis=1)])
    np.testing.assert_array_equal(locator.detector_at(centres[:, 0], centres[:, 1]), np.arange(189))
    # Middle of the gap between the central CCD and its right neighbour; a corner raft.
    gap_x = 0.5 * 42.25 * ARCSEC_PER_MM
    corner = 2.0 * 127.0 * ARCSEC_PER_MM
    assert locator.detector_at(np.array([gap_x, corner]), np.array([0.0, corner])).tolist() == [
        -1,
        -1,
    ]
    assert len(decam_like_focal_plane().detectors) == 62


def test_overlapping_detectors_are_refused() -> None:
    with pytest.raises(ValueError, match="overlap"):
        FocalPlaneConfig(
            name="bad",
            pixel_size_um=10,
            pixel_scale=0.2,
            field_radius_deg=1,
            detectors=(
                Detector(name="a", x_mm=0, y_mm=0, nx=100, ny=100),
                Detector(name="b", x_mm=0.5, y_mm=0, nx=100, ny=100),
            ),
        )


def test_small_cell_inside_a_ccd_is_kept_and_one_across_a_gap_is_rejected() -> None:
    assert _one_visit((0.0, 0.0), 6.0) == (True, True)
    assert _one_visit((100.0, -250.0), 50.0, angle=0.7) == (True, True)
    gap_x = 0.5 * 42.25 * ARCSEC_PER_MM  # the gap is 1.29 mm = 25.8" wide
    assert _one_visit((gap_x, 0.0), 30.0) == (True, False)  # straddles the gap
    assert _one_visit((gap_x, 0.0), 6.0) == (False, False)  # lies inside the gap
    # Near a CCD's outer edge: crossing it is rejected, just inside is kept.
    edge = 0.5 * CCD_SIDE
    assert _one_visit((edge - 10.0, 0.0), 19.0) == (True, True)
    assert _one_visit((edge - 10.0, 0.0), 21.0) == (True, False)
    # A rotated cell's corner reaches further than its side.
    assert _one_visit((edge - 10.0, 0.0), 19.0, angle=np.pi / 4) == (True, False)


def test_classification_matches_brute_force_sampling() -> None:
    rng = np.random.default_rng(2)
    centres = rng.uniform(-900.0, 900.0, size=(300, 2))
    offsets = rng.uniform(-300.0, 300.0, size=(4, 2))
    angles = rng.uniform(0.0, 2 * np.pi, size=4)
    size = 40.0
    covered, contained = classify_cells(LSST, centres, size, offsets, angles)
    locator = LSST.locator()
    grid = np.linspace(-0.5, 0.5, 41) * size
    su, sv = (g.ravel() for g in np.meshgrid(grid, grid))
    for visit, (offset, angle) in enumerate(zip(offsets, angles, strict=True)):
        cos, sin = np.cos(angle), np.sin(angle)
        dx, dy = centres[:, 0] - offset[0], centres[:, 1] - offset[1]
        px, py = cos * dx + sin * dy, -sin * dx + cos * dy
        x = px[:, None] + su * cos + sv * sin
        y = py[:, None] - su * sin + sv * cos
        ids = locator.detector_at(x, y)
        sampled_contained = (ids[:, 0] >= 0) & np.all(ids == ids[:, :1], axis=1)
        sampled_covered = np.any(ids >= 0, axis=1)
        np.testing.assert_array_equal(contained[:, visit], sampled_contained)
        assert np.all(covered[sampled_covered, visit])
        # Overlaps thinner than the 1" sampling are the only allowed disagreement.
        assert np.sum(covered[:, visit] & ~sampled_covered) <= 2
    assert contained.any() and (covered & ~contained).any()


def test_depth_loss_formula() -> None:
    assert depth_loss_mag(100, 100) == 0.0
    assert depth_loss_mag(100, 80) == pytest.approx(1.25 * np.log10(1.25))
    # Equivalent statement: the point-source S/N scales as sqrt(N).
    assert depth_loss_mag(184, 92) == pytest.approx(2.5 * np.log10(np.sqrt(2.0)))
    assert np.isinf(depth_loss_mag(10, 0))
    stats = rejection_statistics(0.5, n_cells=200, n_visits=40, seed=3)
    covered = stats.n_covering > 0
    np.testing.assert_allclose(
        stats.depth_loss_mag[covered],
        -1.25 * np.log10(1.0 - stats.fraction_rejected[covered]),
    )


def test_rejected_fraction_grows_with_cell_size_cell_by_cell() -> None:
    sizes = (0.1, 0.5, 0.8, default_cell_size_arcmin())
    runs = [rejection_statistics(size, n_cells=400, n_visits=60, seed=7) for size in sizes]
    fractions = np.array([run.fraction_rejected for run in runs])
    # Same cells and visits at every size, so growth holds for each cell, not just on average.
    assert np.all(np.diff(fractions, axis=0) >= 0)
    assert np.all(np.diff(fractions.mean(axis=1)) > 0)
    assert default_cell_size_arcmin() == pytest.approx(250 * 0.2 / 60)


def test_results_are_deterministic_from_the_seed() -> None:
    first = rejection_statistics(0.5, n_cells=300, n_visits=50, dither="spiral", seed=1)
    again = rejection_statistics(0.5, n_cells=300, n_visits=50, dither="spiral", seed=1)
    other = rejection_statistics(0.5, n_cells=300, n_visits=50, dither="spiral", seed=2)
    np.testing.assert_array_equal(first.n_covering, again.n_covering)
    np.testing.assert_array_equal(first.n_kept, again.n_kept)
    assert not np.array_equal(first.n_kept, other.n_kept)


def test_unrotated_rejection_matches_the_grid_geometry() -> None:
    # Without rotation an axis-aligned cell is kept iff it fits in a CCD along x and along y.
    # Per raft pitch P = 127 mm, three CCDs of side L keep 3 (L - s) of the centre
    # positions for cells wider than the gaps, so ~1 - (3 (L - s) / P)^2 is rejected.
    size = 0.8 * 60.0
    stats = rejection_statistics(0.8, n_cells=3000, n_visits=100, rotation="none", seed=4)
    expected = 1.0 - (3.0 * (CCD_SIDE - size) / (127.0 * ARCSEC_PER_MM)) ** 2
    assert stats.fraction_rejected.mean() == pytest.approx(expected, abs=0.01)


def test_paper_cell_sizes_land_in_the_papers_range() -> None:
    results = rejection_survey((0.1, 0.8), ("random", "spiral"), n_cells=600, seed=0)
    low, high = PAPER_REJECTED_RANGE
    for stats in results:
        mean = stats.summary()["mean_rejected"]
        if stats.cell_size_arcmin == 0.1:
            assert 0.5 * low < mean < 2 * low
        else:
            assert 0.6 * high < mean < 1.3 * high
        assert stats.summary()["uncovered_cells"] == 0
        assert stats.summary()["mean_depth_loss_mag"] < 0.15
    table = rejection_table(results)
    assert "3% to 20%" in table
    assert len(table.splitlines()) == 2 + len(results) + 1


def test_dither_patterns_stay_in_the_hexagon() -> None:
    radius = 6300.0
    random = hexagon_offsets(2000, radius, np.random.default_rng(0))
    assert np.all(in_hexagon(random[:, 0], random[:, 1], radius))
    assert np.hypot(*random.T).max() > 0.9 * radius  # fills it, not just its centre
    assert abs(random.mean(axis=0)).max() < 0.05 * radius
    spiral = spiral_offsets(130, radius * np.sqrt(3) / 2)
    assert np.all(in_hexagon(spiral[:, 0], spiral[:, 1], radius * (1 + 1e-12)))
    np.testing.assert_array_equal(spiral[:60], spiral[60:120])  # the pattern cycles


def test_plot_rejection_writes_a_small_png(tmp_path) -> None:
    results = rejection_survey((0.1, 0.5), n_cells=100, n_visits=30)
    path = plot_rejection(results, tmp_path / "rejection.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert path.stat().st_size < 200_000


def test_cli_rejection(tmp_path) -> None:
    runner = CliRunner()
    out = tmp_path / "rejection.png"
    args = ["rejection", "--n-cells", "100", "--n-visits", "30", "--cell-size", "0.5"]
    result = runner.invoke(analyze, [*args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "paper" in result.output and out.exists()
    result = runner.invoke(analyze, [*args, "--json", "--dither", "spiral", "--camera", "decam"])
    assert result.exit_code == 0, result.output
    (summary,) = json.loads(result.output)
    assert summary["dither"] == "spiral" and summary["camera"] == "decam-like"
    assert 0.0 < summary["mean_rejected"] < 1.0
