"""Tests of the coadd -> exposure pixel mapping (cellcoadd.builder.mapping)."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.wcs import WCS, Sip

from cellcoadd.builder.kernels.descriptor import LANCZOS3
from cellcoadd.builder.kernels.warp import warp_planes
from cellcoadd.builder.mapping import PixelMapping, footprint_box, map_box, map_points
from cellcoadd.errors import MappingError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.wcs_utils import pixel_area


def tan_wcs(
    center: tuple[float, float],
    crpix: tuple[float, float],
    pixel_scale: float,
    rotation_deg: float = 0.0,
    sip_strength: float = 0.0,
) -> WCS:
    """TAN (optionally TAN-SIP) WCS; ``crpix`` 1-based as in FITS, scale in arcsec/px."""
    wcs = WCS(naxis=2)
    sip = sip_strength != 0.0
    wcs.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"] if sip else ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = list(center)
    wcs.wcs.crpix = list(crpix)
    theta = np.radians(rotation_deg)
    rotation = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    scale = pixel_scale / 3600.0
    wcs.wcs.cd = np.array([[-scale, 0.0], [0.0, scale]]) @ rotation
    if sip:
        a = np.zeros((5, 5))
        b = np.zeros((5, 5))
        # Quadratic terms of ~1 px at 1000 px from crpix, plus cubic and quartic terms.
        a[2, 0], a[0, 2], a[1, 1] = 1.0e-6, -0.5e-6, 0.8e-6
        b[0, 2], b[2, 0], b[1, 1] = 1.0e-6, 0.6e-6, -0.7e-6
        a[3, 0], b[0, 3], a[1, 2] = 1e-10, -1e-10, 5e-11
        a[4, 0], b[2, 2] = 3e-14, -2e-14
        wcs.sip = Sip(a * sip_strength, b * sip_strength, None, None, wcs.wcs.crpix)
    wcs.wcs.set()
    return wcs


COADD_WCS = tan_wcs((150.0, 2.0), (2001.0, 2001.0), 0.2)
BOX = Box(x_start=1700, x_stop=1950, y_start=2100, y_stop=2350)


def exposure_wcs(sip_strength: float = 0.0) -> WCS:
    """A rotated (30 deg), coarser (0.26"/px) exposure whose centre is offset from the box."""
    return tan_wcs((150.01, 2.02), (1000.5, 2000.5), 0.26, 30.0, sip_strength)


def exact_positions(box: Box, wcs: WCS) -> tuple[np.ndarray, np.ndarray]:
    y_coadd, x_coadd = np.mgrid[box.slices]
    return map_points(COADD_WCS, x_coadd, y_coadd, wcs)


@pytest.mark.parametrize("sip_strength", [0.0, 1.0, 20.0])
def test_error_below_tolerance_at_every_pixel(sip_strength):
    wcs = exposure_wcs(sip_strength)
    mapping = map_box(COADD_WCS, BOX, wcs, tolerance=1e-3)
    assert isinstance(mapping, PixelMapping)
    assert mapping.x.shape == mapping.y.shape == mapping.area_ratio.shape == BOX.shape
    assert mapping.grid_step > 0  # these smooth maps must not need exact evaluation
    x_exact, y_exact = exact_positions(BOX, wcs)
    true_error = np.hypot(mapping.x - x_exact, mapping.y - y_exact).max()
    assert true_error < 1e-3
    assert mapping.max_error <= 1e-3
    # The check points bound the error between them within the documented factor of 2.
    assert true_error <= 2 * mapping.max_error + 1e-9


def test_reported_error_is_honest_at_check_points():
    # A 257-px box with a 32-px grid has nodes every 32 px and check points every 16 px,
    # all on pixel centres, so the error there can be measured exactly.
    box = Box(x_start=1700, x_stop=1957, y_start=2100, y_stop=2357)
    wcs = exposure_wcs(20.0)
    mapping = map_box(COADD_WCS, box, wcs, tolerance=1e-3, grid_step=32)
    assert mapping.grid_step == 32
    x_exact, y_exact = exact_positions(box, wcs)
    error = np.hypot(mapping.x - x_exact, mapping.y - y_exact)
    at_checks = error[::16, ::16]
    at_nodes = error[::32, ::32]
    assert at_nodes.max() < 1e-9
    assert mapping.max_error >= at_checks.max() - 1e-11
    assert mapping.max_error == pytest.approx(at_checks.max(), rel=1e-3, abs=1e-10)


def test_refines_then_falls_back_to_exact():
    wcs = exposure_wcs(20.0)
    coarse = map_box(COADD_WCS, BOX, wcs, tolerance=1e-3, grid_step=64)
    assert coarse.grid_step == 64
    # Tighter than the 64-px grid achieves: the grid is refined until it passes.
    tight = 0.5 * coarse.max_error
    refined = map_box(COADD_WCS, BOX, wcs, tolerance=tight, grid_step=64)
    assert 0 < refined.grid_step < 64
    x_exact, y_exact = exact_positions(BOX, wcs)
    assert np.hypot(refined.x - x_exact, refined.y - y_exact).max() < tight
    # Beyond double-precision reach: every pixel is evaluated exactly.
    exact = map_box(COADD_WCS, BOX, wcs, tolerance=1e-15)
    assert exact.grid_step == 0 and exact.max_error == 0.0
    np.testing.assert_array_equal(exact.x, x_exact)
    np.testing.assert_array_equal(exact.y, y_exact)


@pytest.mark.parametrize("sip_strength", [0.0, 20.0])
def test_area_ratio_matches_pixel_areas(sip_strength):
    wcs = exposure_wcs(sip_strength)
    mapping = map_box(COADD_WCS, BOX, wcs)
    x_exact, y_exact = exact_positions(BOX, wcs)
    rng = np.random.default_rng(1)
    for j, i in zip(rng.integers(0, BOX.ny, 12), rng.integers(0, BOX.nx, 12), strict=True):
        expected = pixel_area(COADD_WCS, BOX.x_start + i, BOX.y_start + j) / pixel_area(
            wcs, x_exact[j, i], y_exact[j, i]
        )
        assert mapping.area_ratio[j, i] == pytest.approx(expected, rel=1e-6)
    # Sanity: the ratio is close to (0.2 / 0.26)^2 and varies with the distortion.
    assert np.abs(mapping.area_ratio / (0.2 / 0.26) ** 2 - 1).max() < 0.02


def test_footprint_box_matches_brute_force():
    mapping = map_box(COADD_WCS, BOX, exposure_wcs(20.0))
    taps_x = set()
    taps_y = set()
    for fx, fy in zip(np.floor(mapping.x).ravel(), np.floor(mapping.y).ravel(), strict=True):
        taps_x.update(range(int(fx) - 2, int(fx) + 4))
        taps_y.update(range(int(fy) - 2, int(fy) + 4))
    expected = Box(
        x_start=min(taps_x), x_stop=max(taps_x) + 1, y_start=min(taps_y), y_stop=max(taps_y) + 1
    )
    assert footprint_box(mapping) == expected
    assert footprint_box(mapping, kernel=LANCZOS3) == expected
    # The footprint is exactly what the warp needs: a cutout of it is warpable.
    cutout = np.zeros((1, *expected.shape))
    warp_planes(
        cutout,
        np.ascontiguousarray(mapping.x - expected.x_start),
        np.ascontiguousarray(mapping.y - expected.y_start),
    )
    with pytest.raises(ValueError, match="kernel taps"):
        warp_planes(
            cutout[:, :, 1:],
            np.ascontiguousarray(mapping.x - expected.x_start - 1),
            np.ascontiguousarray(mapping.y - expected.y_start),
        )


def test_warping_through_mapping_follows_the_sky():
    # A smooth pattern fixed on the sky, sampled by the exposure and resampled onto the
    # coadd box, must match the same pattern evaluated at the coadd pixels' sky positions.
    wcs = exposure_wcs(20.0)
    mapping = map_box(COADD_WCS, BOX, wcs)
    footprint = footprint_box(mapping)
    y_exp, x_exp = np.mgrid[footprint.slices].astype(np.float64)
    ra_exp, dec_exp = wcs.all_pix2world(x_exp, y_exp, 0)

    def pattern(ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        # Periods of ~100 exposure pixels: smooth on the scale of the kernel.
        k = 2 * np.pi / (30.0 / 3600.0)
        return np.cos(k * (ra - 150.0) * 0.6) * np.sin(k * (dec - 2.0) * 0.8 + 0.3)

    image = pattern(ra_exp, dec_exp)[np.newaxis]
    warped = warp_planes(
        image,
        np.ascontiguousarray(mapping.x - footprint.x_start),
        np.ascontiguousarray(mapping.y - footprint.y_start),
    )[0]
    y_coadd, x_coadd = np.mgrid[BOX.slices]
    expected = pattern(*COADD_WCS.all_pix2world(x_coadd, y_coadd, 0))
    # The bound is Lanczos-3's own interpolation error: the normalised kernel does not
    # reproduce linear functions (its first moment reaches 0.02 px near quarter-pixel
    # phases), so a pattern of unit amplitude and ~100 px period is off by ~1e-3.
    assert np.abs(warped - expected).max() < 2e-3
    # A transposed convention would be grossly wrong.
    assert np.abs(warped - expected.T).max() > 0.5


def test_points_off_the_exposure_do_not_crash():
    far_tan = tan_wcs((270.0, 2.0), (1000.5, 2000.5), 0.26)  # other side of the sky
    mapping = map_box(COADD_WCS, BOX, far_tan)
    assert not mapping.is_complete
    with pytest.raises(MappingError):
        footprint_box(mapping)
    # SIP exposures far away: the inverse iteration diverges; map_points gives NaN.
    far_sip = tan_wcs((180.0, 20.0), (1000.5, 2000.5), 0.26, 10.0, sip_strength=50.0)
    x_far, y_far = map_points(COADD_WCS, np.array([1800.0, 0.0]), np.array([2200.0, 0.0]), far_sip)
    assert x_far.shape == (2,)
    assert np.isnan(x_far).all() or np.abs(x_far).min() > 1e5
    mapping = map_box(COADD_WCS, Box(x_start=0, x_stop=20, y_start=0, y_stop=20), far_sip)
    if mapping.is_complete:
        assert not Box(x_start=0, x_stop=4000, y_start=0, y_stop=4000).contains_box(
            footprint_box(mapping)
        )


def test_small_and_empty_boxes():
    wcs = exposure_wcs(1.0)
    tiny = Box(x_start=1800, x_stop=1803, y_start=2200, y_stop=2210)
    mapping = map_box(COADD_WCS, tiny, wcs)
    x_exact, y_exact = exact_positions(tiny, wcs)
    assert mapping.grid_step == 0
    np.testing.assert_array_equal(mapping.x, x_exact)
    np.testing.assert_array_equal(mapping.y, y_exact)
    small = Box(x_start=1800, x_stop=1825, y_start=2200, y_stop=2225)
    mapping = map_box(COADD_WCS, small, wcs)
    x_exact, y_exact = exact_positions(small, wcs)
    assert np.hypot(mapping.x - x_exact, mapping.y - y_exact).max() < 1e-3
    empty = map_box(COADD_WCS, Box(x_start=5, x_stop=5, y_start=0, y_stop=3), wcs)
    assert empty.x.shape == (3, 0)
    with pytest.raises(MappingError):
        footprint_box(empty)


def test_mapping_arrays_are_read_only():
    mapping = map_box(COADD_WCS, BOX, exposure_wcs())
    with pytest.raises(ValueError):
        mapping.x[0, 0] = 1.0


def test_footprint_box_accepts_any_positions_object():
    class Positions:
        x = np.array([[10.2, 11.7]])
        y = np.array([[-3.5, 4.0]])

    assert footprint_box(Positions()) == Box(x_start=8, x_stop=15, y_start=-6, y_stop=8)


def test_unit_area_snapping_matches_numpy_bit_for_bit():
    """The one-pass snapping of area ratios near 1 sets exactly the values numpy's masked
    assignment sets (ratios within the tolerance of 1, at its edge, NaN and infinities)."""
    from cellcoadd.builder.kernels.unit_area import snap_unit_area

    rng = np.random.default_rng(3)
    tolerance = 1e-8
    values = np.concatenate(
        [
            1.0 + rng.normal(0.0, 2e-8, 5000),
            rng.uniform(0.5, 1.5, 1000),
            1.0 + np.array([tolerance, -tolerance, np.nextafter(tolerance, 0.0), 0.0, -0.0]),
            [np.nan, np.inf, -np.inf, 0.0, -0.0],
        ]
    )
    got = values.reshape(-1, 5).copy()
    expected = got.copy()
    snap_unit_area(got, tolerance)
    expected[np.abs(expected - 1.0) < tolerance] = 1.0
    assert np.array_equal(got.view(np.uint64), expected.view(np.uint64))
    assert 0 < np.count_nonzero(got == 1.0) < got.size  # some snapped, some not
