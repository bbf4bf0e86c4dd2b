"""Tests of the normalised Lanczos-3 resampling kernel (cellcoadd.builder.kernels.warp)."""

from __future__ import annotations

import hashlib

import galsim
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellcoadd.builder.kernels.accumulate import accumulate_warped
from cellcoadd.builder.kernels.descriptor import WARP_KERNEL
from cellcoadd.builder.kernels.lanczos import TABLE_WIDTH
from cellcoadd.builder.kernels.mask_warp import warp_mask_or
from cellcoadd.builder.kernels.reference import reference_accumulate, tap_sum
from cellcoadd.builder.kernels.warp import KERNEL_HALF_WIDTH, warp_planes


def reference_warp(plane: np.ndarray, x_src: np.ndarray, y_src: np.ndarray) -> np.ndarray:
    """Direct double loop: normalised sinc(t) sinc(t/3) on taps floor(.)-2 .. floor(.)+3."""
    out = np.zeros(x_src.shape)
    for j in range(x_src.shape[0]):
        for i in range(x_src.shape[1]):
            x, y = x_src[j, i], y_src[j, i]
            taps_x = np.floor(x) + np.arange(-2, 4)
            taps_y = np.floor(y) + np.arange(-2, 4)
            wx = np.sinc(x - taps_x) * np.sinc((x - taps_x) / 3)
            wy = np.sinc(y - taps_y) * np.sinc((y - taps_y) / 3)
            wx /= wx.sum()
            wy /= wy.sum()
            block = plane[np.ix_(taps_y.astype(int), taps_x.astype(int))]
            out[j, i] = wy @ block @ wx
    return out


def affine_positions(
    shape: tuple[int, int],
    origin: tuple[float, float],
    scale: float,
    rotation_deg: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Input positions of an output grid that is rotated and scaled relative to the input."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    theta = np.radians(rotation_deg)
    x_src = origin[0] + scale * (np.cos(theta) * xx - np.sin(theta) * yy)
    y_src = origin[1] + scale * (np.sin(theta) * xx + np.cos(theta) * yy)
    return x_src, y_src


@pytest.fixture(scope="module")
def rotated_job() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three random planes and the positions of a 40x40 output rotated by 30 deg."""
    rng = np.random.default_rng(11)
    planes = rng.normal(size=(3, 80, 90))
    x_src, y_src = affine_positions((40, 40), (40.0, 8.0), 0.2 / 0.26, 30.0)
    return planes, x_src, y_src


def test_matches_direct_reference(rotated_job):
    planes, x_src, y_src = rotated_job
    warped = warp_planes(planes, x_src, y_src)
    for plane, result in zip(planes, warped, strict=True):
        expected = reference_warp(plane, x_src, y_src)
        assert np.abs(result - expected).max() < 1e-12 * np.abs(plane).max()


@settings(max_examples=40, deadline=None)
@given(
    x=st.floats(min_value=2.0, max_value=12.999999, allow_nan=False),
    y=st.floats(min_value=2.0, max_value=12.999999, allow_nan=False),
)
def test_weights_match_reference_and_sum_to_one(x, y):
    # Warping a unit impulse at each input pixel gives that tap's weight.
    n = 17
    impulses = np.zeros((n * n, n, n))
    impulses[np.arange(n * n), np.repeat(np.arange(n), n), np.tile(np.arange(n), n)] = 1.0
    x_src = np.array([[x]])
    y_src = np.array([[y]])
    weights = warp_planes(impulses, x_src, y_src)[:, 0, 0].reshape(n, n)
    assert abs(weights.sum() - 1.0) < 1e-14
    taps_x = np.floor(x) + np.arange(-2, 4)
    wx = np.sinc(x - taps_x) * np.sinc((x - taps_x) / 3)
    taps_y = np.floor(y) + np.arange(-2, 4)
    wy = np.sinc(y - taps_y) * np.sinc((y - taps_y) / 3)
    expected = np.zeros((n, n))
    expected[np.ix_(taps_y.astype(int), taps_x.astype(int))] = np.outer(
        wy / wy.sum(), wx / wx.sum()
    )
    assert np.abs(weights - expected).max() < 1e-14


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_constant_in_constant_out(rotated_job, dtype):
    _, x_src, y_src = rotated_job
    rng = np.random.default_rng(5)
    x_src = x_src + rng.uniform(-0.5, 0.5, x_src.shape)  # arbitrary sub-pixel phases
    constant = np.full((2, 80, 90), 3.7, dtype=dtype)
    warped = warp_planes(constant, x_src, y_src)
    assert np.abs(warped / np.float64(dtype(3.7)) - 1).max() < 1e-12


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_integer_shift_is_exact_copy(dtype):
    rng = np.random.default_rng(2)
    planes = rng.normal(size=(2, 30, 40)).astype(dtype)
    planes[:, 3, 3] = np.nan  # outside every footprint's centre but inside some footprints
    yy, xx = np.mgrid[0:20, 0:25].astype(np.float64)
    # Within 1e-9 px of an integer counts as an integer, on both sides.
    x_src = xx + 5.0 + np.where(xx % 2 == 0, 3e-10, -3e-10)
    y_src = yy + 4.0
    warped = warp_planes(planes, x_src, y_src)
    expected = planes[:, 4:24, 5:30].astype(np.float64)
    assert np.array_equal(warped, expected)


def test_multiplane_equals_separate_planes(rotated_job):
    planes, x_src, y_src = rotated_job
    together = warp_planes(planes, x_src, y_src)
    for p in range(planes.shape[0]):
        alone = warp_planes(planes[p : p + 1], x_src, y_src)[0]
        assert np.array_equal(together[p], alone)


def test_accumulation_with_weight_and_scale(rotated_job):
    planes, x_src, y_src = rotated_job
    rng = np.random.default_rng(9)
    scale = rng.uniform(0.5, 1.5, x_src.shape)
    start = rng.normal(size=(planes.shape[0], *x_src.shape))
    out = start.copy()
    returned = warp_planes(planes, x_src, y_src, out=out, weight=2.5, scale=scale)
    assert returned is out
    warped = warp_planes(planes, x_src, y_src)
    np.testing.assert_allclose(out, start + 2.5 * scale * warped, rtol=1e-14, atol=1e-14)
    # Weight alone, no scale.
    out2 = warp_planes(planes, x_src, y_src, out=np.zeros_like(start), weight=0.25)
    np.testing.assert_array_equal(out2, 0.25 * warped)


@pytest.mark.parametrize("n_planes", [1, 2, 3, 4, 5, 6, 7, 8, 9, 13])
def test_interleaved_accumulation_is_bit_identical_to_warp_planes(n_planes):
    # Every plane count takes its own path through the vector widths (and more than
    # eight overlapping groups); each plane must still get exactly warp_planes' bits.
    rng = np.random.default_rng(n_planes)
    planes = rng.normal(size=(n_planes, 70, 80))
    x_src, y_src = affine_positions((30, 33), (35.0, 6.0), 0.77, 30.0)
    x_src[3] = np.round(x_src[3])  # integral along x only
    x_src[5, :4], y_src[5, :4] = 20.0, 30.0  # integral along both: copied
    weights = rng.uniform(0.5, 2.0, n_planes)
    scales = rng.uniform(0.5, 1.5, (2, *x_src.shape))
    which = rng.integers(-1, 2, n_planes)
    start = rng.normal(size=(n_planes, *x_src.shape))
    pixels = np.ascontiguousarray(planes.transpose(1, 2, 0))
    out = accumulate_warped(pixels, x_src, y_src, start.copy(), weights, scales, which)
    for p in range(n_planes):
        scale = None if which[p] < 0 else scales[which[p]]
        expected = warp_planes(
            planes[p : p + 1], x_src, y_src, start[p : p + 1].copy(), weights[p], scale
        )
        assert np.array_equal(out[p], expected[0]), p


def test_float32_input_matches_float64(rotated_job):
    planes, x_src, y_src = rotated_job
    single = planes.astype(np.float32)
    from_single = warp_planes(single, x_src, y_src)
    from_double = warp_planes(single.astype(np.float64), x_src, y_src)
    assert np.array_equal(from_single, from_double)


@pytest.mark.parametrize("sigma", [2.5, 4.0])
def test_agrees_with_galsim_lanczos3(sigma):
    # GalSim's Lanczos with conserve_dc=True is also flux-normalised (by a different
    # method); on a smooth, well-sampled image the two agree to ~3e-6 of the peak.
    n = 64
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    image = np.exp(-((xx - 31.3) ** 2 + (yy - 30.6) ** 2) / (2 * sigma**2))
    rng = np.random.default_rng(4)
    x_src = rng.uniform(18.0, 45.0, (6, 6))
    y_src = rng.uniform(18.0, 45.0, (6, 6))
    ours = warp_planes(image[np.newaxis], x_src, y_src)[0]
    interpolated = galsim.InterpolatedImage(
        galsim.ImageD(image, scale=1.0),
        x_interpolant=galsim.Lanczos(3, conserve_dc=True),
        normalization="sb",
    )
    centre = (n - 1) / 2  # InterpolatedImage puts the array's true centre at the origin
    theirs = np.array(
        [
            interpolated.xValue(galsim.PositionD(x - centre, y - centre))
            for x, y in zip(x_src.ravel(), y_src.ravel(), strict=True)
        ]
    ).reshape(x_src.shape)
    assert np.abs(ours - theirs).max() < 1e-5 * image.max()


def test_mask_or_reaches_exactly_the_footprint(rotated_job):
    _, x_src, y_src = rotated_job
    mask = np.zeros((80, 90), dtype=np.int32)
    bit_x, bit_y = 40, 30
    mask[bit_y, bit_x] = 4
    mask[0, 0] = 1  # far from every footprint
    result = warp_mask_or(mask, x_src, y_src)
    first_x = np.floor(x_src) - (KERNEL_HALF_WIDTH - 1)
    first_y = np.floor(y_src) - (KERNEL_HALF_WIDTH - 1)
    covers = (
        (first_x <= bit_x)
        & (bit_x < first_x + 2 * KERNEL_HALF_WIDTH)
        & (first_y <= bit_y)
        & (bit_y < first_y + 2 * KERNEL_HALF_WIDTH)
    )
    assert covers.sum() > 0
    assert np.array_equal(result, np.where(covers, 4, 0).astype(np.int32))


def test_mask_or_matches_brute_force(rotated_job):
    _, x_src, y_src = rotated_job
    rng = np.random.default_rng(8)
    mask = np.where(rng.random((80, 90)) < 0.01, 1 << rng.integers(0, 8, (80, 90)), 0)
    mask = mask.astype(np.int32)
    first_x = np.floor(x_src).astype(int) - (KERNEL_HALF_WIDTH - 1)
    first_y = np.floor(y_src).astype(int) - (KERNEL_HALF_WIDTH - 1)
    expected = np.zeros(x_src.shape, dtype=np.int32)
    for index in np.ndindex(x_src.shape):
        block = mask[first_y[index] : first_y[index] + 6, first_x[index] : first_x[index] + 6]
        expected[index] = np.bitwise_or.reduce(block, axis=None)
    assert expected.any() and not expected.all()
    assert np.array_equal(warp_mask_or(mask, x_src, y_src), expected)


def test_mask_or_combines_bits():
    mask = np.zeros((20, 20), dtype=np.int32)
    mask[8, 8] = 1
    mask[10, 11] = 2
    result = warp_mask_or(mask, np.array([[9.5]]), np.array([[9.5]]))
    assert result[0, 0] == 3


@pytest.mark.parametrize(
    ("x", "y", "axis"),
    [
        (1.999, 10.0, "x"),
        (2.0, 10.0, None),
        (16.999, 10.0, None),
        (17.0, 10.0, "x"),
        (10.0, 1.5, "y"),
        (10.0, 17.2, "y"),
    ],
)
def test_taps_outside_input_raise(x, y, axis):
    planes = np.zeros((1, 20, 20))
    x_src = np.full((2, 2), 10.0)
    y_src = np.full((2, 2), 10.0)
    x_src[1, 1] = x
    y_src[1, 1] = y
    if axis is None:
        warp_planes(planes, x_src, y_src)
        warp_mask_or(np.zeros((20, 20), dtype=np.int32), x_src, y_src)
        return
    with pytest.raises(ValueError, match=f"along {axis}"):
        warp_planes(planes, x_src, y_src)
    with pytest.raises(ValueError, match=f"along {axis}"):
        warp_mask_or(np.zeros((20, 20), dtype=np.int32), x_src, y_src)


def test_input_validation():
    planes = np.zeros((1, 20, 20))
    good = np.full((3, 3), 10.0)
    with pytest.raises(ValueError, match="finite"):
        warp_planes(planes, np.full((3, 3), np.nan), good)
    with pytest.raises(ValueError, match="float32 or float64"):
        warp_planes(planes.astype(np.int32), good, good)
    with pytest.raises(ValueError, match="3-D"):
        warp_planes(planes[0], good, good)
    with pytest.raises(ValueError, match="differ in shape"):
        warp_planes(planes, good, np.full((3, 4), 10.0))
    with pytest.raises(ValueError, match="float64"):
        warp_planes(planes, good.astype(np.float32), good)
    with pytest.raises(ValueError, match="out must be"):
        warp_planes(planes, good, good, out=np.zeros((2, 3, 3)))
    with pytest.raises(ValueError, match="scale has shape"):
        warp_planes(planes, good, good, scale=np.ones((2, 2)))
    with pytest.raises(ValueError, match="int32"):
        warp_mask_or(np.zeros((20, 20), dtype=np.int64), good, good)


def smooth_positions(shape: tuple[int, int], seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Input positions (around (60, 60)) of a ``shape`` output under a random smooth
    mapping: rotation, scale and shear, plus quadratic and sinusoidal terms."""
    rng = np.random.default_rng(seed)
    a, b, c, d = rng.uniform(-0.6, 0.6, 4)
    q = rng.uniform(-2e-3, 2e-3, 6)
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    xx -= shape[1] / 2
    yy -= shape[0] / 2
    x_src = 60.3 + a * xx + b * yy + q[0] * xx**2 + q[1] * xx * yy + q[2] * np.sin(yy / 7)
    y_src = 61.7 + c * xx + d * yy + q[3] * yy**2 + q[4] * xx * yy + q[5] * np.cos(xx / 5)
    return x_src, y_src


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_value_depends_only_on_the_position(seed):
    # The builder warps a large region once and cuts cells out of it: every output
    # pixel must get the same bits wherever it lies in the output (vector lanes or
    # scalar remainders, first column, box size) and whatever the number of planes.
    rng = np.random.default_rng(100 + seed)
    planes = rng.normal(size=(6, 130, 130))
    planes[:, 60:62, 50:53] = rng.normal(size=(6, 2, 3)) * 1e6  # far-off values too
    shape = (37, 53)
    x_src, y_src = smooth_positions(shape, seed)
    x_src[5, 7], y_src[5, 7] = 50.0, 70.0  # integral: copied
    x_src[9, 11:20] = np.round(x_src[9, 11:20])  # integral along x only
    weights = rng.uniform(0.5, 2.0, 6)
    scales = rng.uniform(0.5, 1.5, (2, *shape))
    which = np.array([0, 0, 0, 1, -1, 0])
    pixels = np.ascontiguousarray(planes.transpose(1, 2, 0))

    def warp(n_planes: int, rows: slice, cols: slice) -> np.ndarray:
        x, y = x_src[rows, cols], y_src[rows, cols]
        return accumulate_warped(
            np.ascontiguousarray(pixels[..., :n_planes]),
            np.ascontiguousarray(x),
            np.ascontiguousarray(y),
            np.zeros((n_planes, *x.shape)),
            weights[:n_planes],
            np.ascontiguousarray(scales[:, rows, cols]),
            which[:n_planes],
        )

    everything = slice(None)
    whole = warp(6, everything, everything)
    assert np.array_equal(warp(5, everything, everything), whole[:5])
    unit = warp_planes(planes, x_src, y_src)
    for row0, col0, height, width in [
        (0, 0, 37, 1),
        (0, 1, 37, 52),
        (3, 5, 1, 17),
        (7, 11, 13, 9),
        (1, 3, 35, 47),
        (20, 27, 17, 26),
        (36, 52, 1, 1),
    ]:
        rows, cols = slice(row0, row0 + height), slice(col0, col0 + width)
        for n_planes in (5, 6):
            part = warp(n_planes, rows, cols)
            assert np.array_equal(part, whole[:n_planes, rows, cols]), (row0, col0, n_planes)
        by_plane = warp_planes(
            planes[3:],
            np.ascontiguousarray(x_src[rows, cols]),
            np.ascontiguousarray(y_src[rows, cols]),
        )
        assert np.array_equal(by_plane, unit[3:, rows, cols])


def test_long_rows_are_cut_without_a_trace():
    # Rows longer than a table are resampled in runs; a pixel's bits do not depend on the
    # run it falls in.
    rng = np.random.default_rng(7)
    planes = rng.normal(size=(4, 100, 300))
    n_cols = 2 * TABLE_WIDTH + 41
    yy, xx = np.mgrid[0:3, 0:n_cols].astype(np.float64)
    x_src = 20.25 + 0.45 * xx + 0.3 * yy + 0.2 * np.sin(xx / 9)
    y_src = 30.4 + 0.05 * xx + 0.7 * yy + 0.3 * np.cos(xx / 13)
    pixels = np.ascontiguousarray(planes.transpose(1, 2, 0))
    whole = accumulate_warped(pixels, x_src, y_src, np.zeros((4, *x_src.shape)), np.ones(4))
    for col0 in (1, TABLE_WIDTH - 3, TABLE_WIDTH + 17, 2 * TABLE_WIDTH - 36):
        cols = slice(col0, col0 + 37)
        part = accumulate_warped(
            pixels,
            np.ascontiguousarray(x_src[:, cols]),
            np.ascontiguousarray(y_src[:, cols]),
            np.zeros((4, 3, 37)),
            np.ones(4),
        )
        assert np.array_equal(part, whole[:, :, cols]), col0


def test_accumulating_equals_warping_into_zeros_then_adding():
    # How the builder uses a warp of a large region: into zeros, then added to the sums.
    rng = np.random.default_rng(12)
    planes = rng.normal(size=(5, 130, 130))
    x_src, y_src = smooth_positions((29, 31), 5)
    pixels = np.ascontiguousarray(planes.transpose(1, 2, 0))
    weights = rng.uniform(0.5, 2.0, 5)
    scales = rng.uniform(0.5, 1.5, (1, *x_src.shape))
    which = np.array([0, 0, -1, 0, 0])
    start = rng.normal(size=(5, *x_src.shape))
    direct = accumulate_warped(pixels, x_src, y_src, start.copy(), weights, scales, which)
    into_zeros = accumulate_warped(
        pixels, x_src, y_src, np.zeros_like(start), weights, scales, which
    )
    assert np.array_equal(direct, start + into_zeros)


def _reference(planes, x_src, y_src, start, weights, scales, which) -> np.ndarray:
    out = start.copy()
    reference_accumulate(planes, x_src, y_src, out, weights, scales, which)
    return out


@pytest.mark.parametrize("n_planes", [1, 2, 3, 4, 5, 6, 7, 8, 9, 13])
def test_fast_kernel_is_bit_identical_to_the_plain_reference(n_planes):
    # The SIMD sums, weight tables, row runs and prefetches change nothing: every value
    # is the plain per-pixel, per-plane, per-tap definition of kernels/reference.py.
    rng = np.random.default_rng(40 + n_planes)
    planes = rng.normal(size=(n_planes, 130, 130))
    planes[:, 60:62, 50:53] = rng.normal(size=(n_planes, 2, 3)) * 1e6  # far-off values
    planes[:, 100, 100] = np.nan  # inside some footprints only
    yy, xx = np.mgrid[0:9, 0 : TABLE_WIDTH + 21].astype(np.float64)  # rows cut in runs
    x_src = 10.3 + 0.41 * xx + 0.2 * yy + 0.3 * np.sin(yy / 3)
    y_src = 20.7 + 0.05 * xx + 0.8 * yy + 0.2 * np.cos(xx / 11)
    x_src[2] = np.round(x_src[2])  # integral along x only
    x_src[4, :5], y_src[4, :5] = 50.0, 30.0  # integral along both: a copy
    x_src[6, 3], y_src[6, 3] = 100.0, 100.0  # a copy of the NaN pixel, NaN around it
    weights = rng.uniform(0.5, 2.0, n_planes)
    scales = rng.uniform(0.5, 1.5, (2, *x_src.shape))
    which = rng.integers(-1, 2, n_planes)
    start = rng.normal(size=(n_planes, *x_src.shape))
    pixels = np.ascontiguousarray(planes.transpose(1, 2, 0))
    fast = accumulate_warped(pixels, x_src, y_src, start.copy(), weights, scales, which)
    reference = _reference(planes, x_src, y_src, start, weights, scales, which)
    assert np.isnan(fast).any() and not np.isnan(fast).all()
    assert np.array_equal(fast, reference, equal_nan=True)
    # warp_planes: into zeros, weight one, no scale
    into_zeros = _reference(
        planes,
        x_src,
        y_src,
        np.zeros_like(start),
        np.ones(n_planes),
        np.ones((1, 1, 1)),
        np.full(n_planes, -1),
    )
    assert np.array_equal(warp_planes(planes, x_src, y_src), into_zeros, equal_nan=True)


def test_reference_matches_the_sinc_definition(rotated_job):
    # The reference's weights are Lanczos-3 itself, not just the fast kernel's
    planes, x_src, y_src = rotated_job
    out = _reference(
        planes,
        x_src,
        y_src,
        np.zeros((3, *x_src.shape)),
        np.ones(3),
        np.ones((1, 1, 1)),
        -np.ones(3, dtype=np.int64),
    )
    for plane, result in zip(planes, out, strict=True):
        expected = reference_warp(plane, x_src, y_src)
        assert np.abs(result - expected).max() < 1e-12 * np.abs(plane).max()


@pytest.mark.parametrize("n_terms", [1, 2, 3, 5, 6, 7, 12])
def test_tap_sum_order(n_terms):
    # Pairs, round after round: for six ((t0 + t1) + (t2 + t3)) + (t4 + t5). Terms of very
    # different sizes make the rounding of each order visible.
    terms = np.array([1e16, 1.0, -1e16, 3.0, 2.5, -7.0, 1e-3, 4.0, 1e15, -1e15, 0.5, 9.0])
    terms = terms[:n_terms]
    values = list(terms)
    while len(values) > 1:
        pairs = [values[k] + values[k + 1] for k in range(0, len(values) - 1, 2)]
        values = pairs + values[2 * len(pairs) :]
    assert tap_sum(terms.copy()) == values[0]
    if n_terms == 6:
        t = terms
        assert tap_sum(t.copy()) == ((t[0] + t[1]) + (t[2] + t[3])) + (t[4] + t[5])


def test_kernel_descriptor_is_what_the_warp_reads():
    assert (WARP_KERNEL.name, WARP_KERNEL.half_width, WARP_KERNEL.taps) == ("lanczos3", 3, 6)
    assert WARP_KERNEL.tap_range(7.2, 9.9) == (5, 13)  # floor(x) - 2 .. floor(x) + 3
    assert WARP_KERNEL.tap_range(-0.5, -0.5) == (-3, 3)
    # the taps the kernel reads are exactly the descriptor's: one input pixel more on
    # either side raises
    planes = np.zeros((1, 20, 20))
    start, stop = WARP_KERNEL.tap_range(2.0, 16.0)
    assert (start, stop) == (0, 20)
    warp_planes(planes, np.array([[2.0, 16.0]]), np.array([[2.0, 16.0]]))
    for x in (1.99, 17.0):
        with pytest.raises(ValueError, match="taps"):
            warp_planes(planes, np.array([[x]]), np.array([[5.0]]))


# SHA-256 of (accumulated, sub-box into zeros, warp_planes) on _pinned_job(n_planes): the
# kernel's bits may not change when it is made faster (a change of the arithmetic is a
# documented decision, and updates these).
_PINNED_DIGESTS = {
    1: (
        "8c620d8e7583d58dc77101347150164badd74e971900785730964df9a124e516",
        "63e7145608e8f4988ce190dd406add2992dc683b3ab42a4eec61d6a8e14bdbd7",
        "4f5f62b0b5210f2b85241e98fb496f88bb50222ed86039a119b4369b2802c663",
    ),
    2: (
        "fd87a7ad6eaffdddf68db1a22b24f38c8ad37f152d26688e7109a78dbf3b4e23",
        "9a6a4583c8f0dedace9116f87c62c32ce7bf2e788f2a78a835b9242b0d4d66a3",
        "f4e048550f318c02cf7a9827eccb0d2b5eb1a1fdec7cb5b2a3106b5fbf935415",
    ),
    3: (
        "ccfc22584028a6d621e7bcd7d3e56140339bc3c546609a0e0b932c9c38d8ecc7",
        "fadc945c5d48a1675e0d1385360aba82d6d2ba518ae7dcbdc692ff76373f8717",
        "598368c5d040e9b47d6fd49d1fcb2e60fceb0604d88778694cbd3baccce5defc",
    ),
    4: (
        "d7f9f9b6de0ede348023135b1cb54848f935b87aaea50e42f17142a18e8578be",
        "82bcc207c18c40513912bdccb0a047f0597afe8ed2415b67c096f1b5b192ad00",
        "766ba10b74d43133791b4cdd933aa37a50f4dea3c8ecbd0763f315d33709b253",
    ),
    5: (
        "c7f096d515d0a81e26a0e2b05555ad9eab484837e79500d40e3c411876eef657",
        "aa5121c0a8b3c714ed7634138fcfd70f3dc56d5b47cf4ffb286558def7c3644b",
        "017494d498c10142c80eee32ec1057c3e45cb7247cc61ff8b76985295d1dcfc2",
    ),
    6: (
        "56bbb9bd528633c2b82442d058ca52e61f5ece13ea460b8dee41ae17324f90ef",
        "05ce9c6c3d8a69d3977dd244eaed4b3562a046c39f7bbfdc9704ba64a5ce05d5",
        "706c67eaabcacd6b877d2605760b02269cf74019b486752ec85e3b9ba1a268b4",
    ),
    7: (
        "19f0e5932c49308754ca480149f18490d2d648d971234ccc20f6ba66fc2ca8b7",
        "3b6591345c9079d845df4cdc24f73d4f31dbf1742bd0e6231caf575e2d83c76a",
        "250a4b78e71370a442ef1680fae32338e3acaf46e219f99bc42dd6bfc39f77a0",
    ),
    8: (
        "e7767f0ded91e710066350484559984117fca80e42a54b0e8e010154db9ede49",
        "78371da3764bd74a07ee703152cb3e3e7778b56f15a5b4262906b81f8568c8be",
        "73e6dcd0d944b5b04ccf01e884c99544a9a328cae1e81da8ec5010fb987a4d78",
    ),
    9: (
        "3df661fdddc2e09b02dae9e2626dd555a7c660a6064e579a3ef81c9abcf1ba93",
        "91e4f968dfb510bd89b8b723db31086f074fe5db6dc996f2069eb319b6d9491c",
        "598a17b52bc19593a5784cd355832e0eb8ff387801268f59c1e0cc04d9ed0efe",
    ),
    13: (
        "a380b4fd0bc6ee29e524352fbdb0b38cd1ac45444737e59fdb21661d192f159c",
        "5f0bff9b079bfe168f959d2f583b223e5f87f60fec4a9c5fe92b0be218618dec",
        "2ee2467258007c2876bc3d5abb92358dd0c1708dd5f9f544b3b35c56887551c9",
    ),
}
_COS30, _SIN30 = 0.8660254037844387, 0.5  # written out: no libm in the positions


def _pinned_job(n_planes: int) -> tuple[np.ndarray, ...]:
    """A 30-degree rotated, dithered output of 23 x (TABLE_WIDTH + 45) pixels (rows in
    runs, a last partial group of rows) over random planes with huge, NaN and infinite
    pixels; integral positions along x, y and both; taps on the first and last input rows
    and columns; positions within 1e-9 of an integer."""
    rng = np.random.default_rng(1000 + n_planes)
    ny_in, nx_in = 170, 400
    planes = rng.normal(size=(n_planes, ny_in, nx_in))
    planes[:, 70:72, 60:63] *= 1e6
    planes[:, 120, 300] = np.nan
    planes[:, 40, 350] = np.inf
    shape = (23, TABLE_WIDTH + 45)
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    scale = 0.2 / 0.26
    x_src = 32.0 + scale * (_COS30 * xx - _SIN30 * yy) + rng.uniform(-0.5, 0.5, shape)
    y_src = 10.0 + scale * (_SIN30 * xx + _COS30 * yy) + rng.uniform(-0.5, 0.5, shape) * 0.3
    x_src[3] = np.floor(x_src[3])
    y_src[5] = np.floor(y_src[5])
    x_src[7, 10:20], y_src[7, 10:20] = np.floor(x_src[7, 10:20]), np.floor(y_src[7, 10:20])
    x_src[8, 0], y_src[8, 0] = 300.0, 120.0  # a copy of the NaN pixel
    x_src[9, 1], y_src[9, 1] = 2.0, 2.0  # taps on the first input row and column
    x_src[9, 2], y_src[9, 2] = 2.0 + 1e-10, 3.0 - 1e-10
    x_src[9, 3], y_src[9, 3] = nx_in - 3.5, ny_in - 3.0 - 1e-3  # taps on the last ones
    x_src[10, 4:12], y_src[10, 4:12] = 299.7 + 0.1 * np.arange(8), 120.2
    x_src[11, 5:9], y_src[11, 5:9] = 350.5, 40.5
    weights = rng.uniform(0.5, 2.0, n_planes)
    scales = rng.uniform(0.5, 1.5, (2, *shape))
    which = rng.integers(-1, 2, n_planes)
    start = rng.normal(size=(n_planes, *shape))
    return planes, x_src, y_src, weights, scales, which, start


@pytest.mark.parametrize("n_planes", sorted(_PINNED_DIGESTS))
def test_kernel_bits_are_pinned(n_planes):
    planes, x_src, y_src, weights, scales, which, start = _pinned_job(n_planes)
    pixels = np.ascontiguousarray(planes.transpose(1, 2, 0))
    accumulated = accumulate_warped(pixels, x_src, y_src, start.copy(), weights, scales, which)
    # the definition first, so that a changed digest is known to be the kernel's doing
    reference = _reference(planes, x_src, y_src, start, weights, scales, which)
    assert np.array_equal(accumulated, reference, equal_nan=True)
    assert np.isnan(accumulated).any() and np.isinf(accumulated).any()
    rows, cols = slice(2, 19), slice(7, 68)
    part = accumulate_warped(
        pixels,
        np.ascontiguousarray(x_src[rows, cols]),
        np.ascontiguousarray(y_src[rows, cols]),
        np.zeros((n_planes, 17, 61)),
        weights,
    )
    unit = warp_planes(planes, x_src, y_src)
    digests = tuple(hashlib.sha256(a.tobytes()).hexdigest() for a in (accumulated, part, unit))
    assert digests == _PINNED_DIGESTS[n_planes]
