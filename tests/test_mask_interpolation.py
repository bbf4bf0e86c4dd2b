"""Tests of the bad-pixel interpolation kernel (cellcoadd.builder.kernels.mask_interpolation)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from cellcoadd.builder.kernels.mask_interpolation import (
    DEFAULT_MAX_RADIUS,
    ISOLATED_VARIANCE_RATIO,
    interpolate_bad_pixels,
    interpolation_variance_ratio,
)


def random_mask(rng: np.random.Generator, shape: tuple[int, int], *, edges: bool) -> np.ndarray:
    """Scattered bad pixels, bad columns and rows, small and big holes; with ``edges`` also
    holes touching every side and a corner."""
    ny, nx = shape
    bad = rng.random(shape) < 0.05
    bad[:, nx // 3] = True
    bad[ny // 4, 5 : nx - 5] = True
    for _ in range(12):
        h, w = rng.integers(1, 6, size=2)
        y, x = rng.integers(4, ny - h - 4), rng.integers(4, nx - w - 4)
        bad[y : y + h, x : x + w] = True
    bad[ny // 2 - 9 : ny // 2 + 9, 2 * nx // 3 - 12 : 2 * nx // 3 + 12] = True
    if edges:
        bad[:7, 10:30] = True
        bad[-3:, :] = True
        bad[20:40, :12] = True
        bad[30:45, -20:] = True
        bad[:10, -10:] = True
    else:
        bad[:4, :] = bad[-4:, :] = bad[:, :4] = bad[:, -4:] = False
    return bad


def chebyshev_reachable(bad: np.ndarray, radius: int) -> np.ndarray:
    """True where a good pixel lies within ``radius`` (Chebyshev distance)."""
    good = (~bad).astype(np.uint8)
    return ndimage.maximum_filter(good, size=2 * radius + 1, mode="constant", cval=0) > 0


def interpolated(pixels: np.ndarray, bad: np.ndarray, **kwargs) -> tuple[np.ndarray, np.ndarray]:
    out = np.ascontiguousarray(pixels, dtype=np.float64).copy()
    unfilled = interpolate_bad_pixels(out, bad, **kwargs)
    return out, unfilled


@pytest.mark.parametrize("edges", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_constant_is_reproduced(seed: int, edges: bool) -> None:
    rng = np.random.default_rng(seed)
    bad = random_mask(rng, (80, 96), edges=edges)
    values = np.array([3.7, -1.25e3, 1e-5, 0.0])
    pixels = np.broadcast_to(values, bad.shape + (4,))
    out, unfilled = interpolated(pixels, bad)
    assert not unfilled.any()
    np.testing.assert_allclose(out, pixels, rtol=1e-12, atol=0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_linear_gradient_is_reproduced_away_from_edges(seed: int) -> None:
    rng = np.random.default_rng(seed)
    bad = random_mask(rng, (80, 96), edges=False)
    y, x = np.mgrid[0:80, 0:96].astype(np.float64)
    planes = np.stack([2.0 + 0.3 * x - 0.7 * y, -5.0 * x + 1e-3 * y, 100.0 + 0 * x], axis=-1)
    out, unfilled = interpolated(planes, bad)
    assert not unfilled.any()
    np.testing.assert_allclose(out, planes, rtol=0, atol=1e-10 * np.abs(planes).max())


def test_gradient_error_bounded_with_edge_holes() -> None:
    rng = np.random.default_rng(7)
    bad = random_mask(rng, (80, 96), edges=True)
    y, x = np.mgrid[0:80, 0:96].astype(np.float64)
    gx, gy = 0.3, -0.7
    plane = (1.0 + gx * x + gy * y)[..., None]
    out, unfilled = interpolated(plane, bad, max_radius=16)
    assert not unfilled.any()
    bound = np.hypot(gx, gy) * np.sqrt(2) * 16
    assert np.abs(out - plane).max() <= bound
    # Isolated bad pixels away from the edge use the plane: exact.
    isolated = bad & (ndimage.convolve(bad.astype(int), np.ones((3, 3), int), mode="constant") == 1)
    isolated[:3] = isolated[-3:] = False
    isolated[:, :3] = isolated[:, -3:] = False
    assert isolated.sum() > 50
    np.testing.assert_allclose(out[isolated], plane[isolated], rtol=0, atol=1e-10)


def test_planes_share_the_weights() -> None:
    rng = np.random.default_rng(3)
    bad = random_mask(rng, (64, 72), edges=True)
    a = rng.normal(size=bad.shape) + np.linspace(0, 4, 72)
    b = rng.normal(size=bad.shape) ** 3
    out, _ = interpolated(np.stack([a, b, a + 3 * b], axis=-1), bad)
    scale = np.abs(out).max()
    np.testing.assert_allclose(
        out[..., 2], out[..., 0] + 3 * out[..., 1], rtol=0, atol=1e-12 * scale
    )
    # One plane at a time gives the same bits as all planes together.
    only_b, _ = interpolated(b[..., None], bad)
    assert np.array_equal(only_b[..., 0], out[..., 1])


def test_weights_sum_to_one_and_match_variance_ratio() -> None:
    """Delta-function planes read the weights of every bad pixel off directly."""
    rng = np.random.default_rng(4)
    shape = (13, 15)
    bad = rng.random(shape) < 0.3
    bad[4:9, 5:10] = True
    bad[0, :6] = True
    deltas = np.eye(bad.size).reshape(shape + (bad.size,))
    weights, unfilled = interpolated(deltas, bad)
    assert not unfilled.any()
    ratio = interpolation_variance_ratio(bad)
    w = weights[bad]  # (n_bad, n_pixels): each row the weights of one bad pixel
    assert np.all(w[:, bad.ravel()] == 0)  # never a bad pixel's value
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose((w**2).sum(axis=1), ratio[bad], rtol=1e-12)
    assert np.all(ratio[~bad] == 1.0)


def test_isolated_pixel_is_gaussian_mean_with_documented_variance_ratio() -> None:
    bad = np.zeros((21, 21), dtype=bool)
    bad[10, 10] = True
    d = np.arange(-3, 4)
    g = np.exp(-0.5 * (d[:, None] ** 2 + d[None, :] ** 2))
    g[3, 3] = 0.0
    g /= g.sum()
    expected = (g**2).sum()
    ratio = interpolation_variance_ratio(bad)
    assert ratio[10, 10] == pytest.approx(expected, rel=1e-12)
    assert ratio[10, 10] == pytest.approx(ISOLATED_VARIANCE_RATIO, abs=5e-7)
    values = np.random.default_rng(5).normal(size=(21, 21, 1))
    out, _ = interpolated(values, bad)
    assert out[10, 10, 0] == pytest.approx((g * values[7:14, 7:14, 0]).sum(), rel=1e-12)


def test_independent_of_visiting_order_and_of_bad_values() -> None:
    rng = np.random.default_rng(6)
    bad = random_mask(rng, (70, 90), edges=True)
    pixels = rng.normal(size=bad.shape + (3,))
    pixels[..., 0] += np.linspace(-2, 5, 90)
    out, unfilled = interpolated(pixels, bad)
    scale = np.abs(out).max()
    transposed, unfilled_t = interpolated(pixels.transpose(1, 0, 2), bad.T.copy())
    assert np.array_equal(unfilled_t, unfilled.T)
    np.testing.assert_allclose(transposed, out.transpose(1, 0, 2), rtol=0, atol=1e-12 * scale)
    flipped, _ = interpolated(pixels[::-1, ::-1], bad[::-1, ::-1].copy())
    np.testing.assert_allclose(flipped, out[::-1, ::-1], rtol=0, atol=1e-12 * scale)
    # Bad pixels' input values are never read: NaN or garbage there changes nothing.
    garbage = pixels.copy()
    garbage[bad] = np.nan
    out_nan, _ = interpolated(garbage, bad)
    assert np.array_equal(out_nan, out)
    garbage[bad] = 1e30
    out_big, _ = interpolated(garbage, bad)
    assert np.array_equal(out_big, out)


def test_good_pixels_untouched_bit_for_bit() -> None:
    rng = np.random.default_rng(8)
    bad = random_mask(rng, (60, 60), edges=True)
    pixels = rng.normal(size=bad.shape + (5,)) * 10.0 ** rng.integers(-300, 300, size=5)
    pixels[~bad] *= -1  # includes -0.0-like sign bits
    out, _ = interpolated(pixels, bad)
    assert np.array_equal(out[~bad].view(np.uint64), pixels[~bad].view(np.uint64))
    assert not np.array_equal(out[bad], pixels[bad])


def test_uninterpolable_pixels_reported_and_zeroed() -> None:
    bad = np.ones((30, 40), dtype=bool)
    pixels = np.full(bad.shape + (2,), 7.0)
    out, unfilled = interpolated(pixels, bad)
    assert unfilled.all()
    assert np.all(out == 0.0)
    assert np.all(interpolation_variance_ratio(bad) == 0.0)

    bad = np.zeros((120, 130), dtype=bool)
    bad[10:110, 15:125] = True
    pixels = np.full(bad.shape + (2,), -2.5)
    out, unfilled = interpolated(pixels, bad, max_radius=10)
    expected = bad & ~chebyshev_reachable(bad, 10)
    assert expected.sum() > 0
    assert np.array_equal(unfilled, expected)
    assert np.all(out[unfilled] == 0.0)
    filled = bad & ~unfilled
    np.testing.assert_allclose(out[filled], -2.5, rtol=1e-12)
    # The default radius, 32 px, leaves only the hole's centre.
    _, unfilled = interpolated(pixels, bad)
    assert 0 < unfilled.sum() < expected.sum()
    assert np.array_equal(unfilled, bad & ~chebyshev_reachable(bad, DEFAULT_MAX_RADIUS))


def test_white_noise_variance_matches_sum_of_squared_weights() -> None:
    rng = np.random.default_rng(9)
    shape = (60, 70)
    bad = np.zeros(shape, dtype=bool)
    bad[10, 10] = True  # isolated
    bad[30:35, 20:25] = True  # small hole
    bad[0, 40] = True  # on the edge
    bad[20:50, 45:65] = True  # big hole
    bad[55:, :8] = True  # corner hole
    probes = [(10, 10), (32, 22), (30, 20), (0, 40), (35, 55), (20, 45), (59, 0)]
    n_real = 4000
    noise_sigma = 2.0
    pixels = rng.normal(scale=noise_sigma, size=shape + (n_real,))
    out, unfilled = interpolated(pixels, bad)
    assert not unfilled.any()
    ratio = interpolation_variance_ratio(bad)
    assert ratio[10, 10] == pytest.approx(ISOLATED_VARIANCE_RATIO, abs=5e-7)
    for y, x in probes:
        expected = noise_sigma**2 * ratio[y, x]
        measured = out[y, x].var(ddof=1)
        tolerance = 3 * expected * np.sqrt(2 / (n_real - 1))
        assert abs(measured - expected) < tolerance, (y, x, measured, expected)
        assert abs(out[y, x].mean()) < 3 * np.sqrt(expected / n_real)


def test_rejects_bad_arguments() -> None:
    bad = np.zeros((4, 5), dtype=bool)
    bad[1, 1] = True
    with pytest.raises(ValueError):
        interpolate_bad_pixels(np.zeros((4, 5)), bad)
    with pytest.raises(ValueError):
        interpolate_bad_pixels(np.zeros((4, 5, 1), dtype=np.float32), bad)
    with pytest.raises(ValueError):
        interpolate_bad_pixels(np.zeros((5, 4, 1)), bad)
    with pytest.raises(ValueError):
        interpolate_bad_pixels(np.zeros((4, 5, 1)), bad.astype(np.uint8))
    with pytest.raises(ValueError):
        interpolate_bad_pixels(np.zeros((4, 5, 1)), bad, sigma=0.0)
    with pytest.raises(ValueError):
        interpolate_bad_pixels(np.zeros((4, 5, 1)), bad, max_radius=0)


@st.composite
def masks(draw: st.DrawFn) -> np.ndarray:
    ny = draw(st.integers(1, 40))
    nx = draw(st.integers(1, 40))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    bad = rng.random((ny, nx)) < draw(st.floats(0.0, 0.6))
    for _ in range(draw(st.integers(0, 4))):
        y0, y1 = sorted(rng.integers(0, ny + 1, size=2))
        x0, x1 = sorted(rng.integers(0, nx + 1, size=2))
        bad[y0:y1, x0:x1] = True
    return bad


@settings(max_examples=150, deadline=None)
@given(
    bad=masks(),
    value=st.floats(-1e6, 1e6, allow_nan=False).filter(lambda v: abs(v) > 1e-6),
    sigma=st.sampled_from([0.5, 1.0, 1.7]),
    max_radius=st.integers(1, DEFAULT_MAX_RADIUS),
)
def test_constant_property(bad: np.ndarray, value: float, sigma: float, max_radius: int) -> None:
    pixels = np.full(bad.shape + (2,), value)
    pixels[..., 1] = -2 * value
    out, unfilled = interpolated(pixels, bad, sigma=sigma, max_radius=max_radius)
    expected_unfilled = bad & ~chebyshev_reachable(bad, max_radius)
    assert np.array_equal(unfilled, expected_unfilled)
    filled = ~unfilled
    np.testing.assert_allclose(out[filled], pixels[filled], rtol=1e-12, atol=0)
    assert np.all(out[unfilled] == 0.0)
