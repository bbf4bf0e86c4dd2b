"""Interpolation of an exposure's bad (masked) pixels before the warp, identically in every plane.

Method
------
Each bad pixel is replaced by a *moving least-squares plane fit* to the good pixels around it:
the plane ``a + b dx + c dy`` minimising ``sum_i g_i (v_i - a - b dx_i - c dy_i)^2`` over the
good pixels ``i`` of a square window centred on the bad pixel, with isotropic Gaussian weights
``g_i = exp(-(dx_i^2 + dy_i^2) / (2 s^2))``, evaluated at the bad pixel (``a``). The result is a
fixed linear combination ``sum_i w_i v_i`` whose weights depend only on the mask, so

* the same weights are applied to every plane (image, K noise realizations, variance): the
  interpolation commutes with adding signal and noise;
* ``sum_i w_i = 1`` (the weights are divided by their sum), so a constant is reproduced
  exactly up to rounding, and a linear gradient is reproduced exactly wherever the plane is
  used;
* for a bad pixel whose good neighbours are symmetric about it (an isolated bad pixel, a
  one-pixel-wide bad column) the fitted slope drops out and the value is the normalised
  Gaussian-weighted mean of the good pixels, the smallest-variance estimate for that
  window;
* the weights come from the *original* good pixels only (never from bad pixels, whatever
  their values, including NaN, and never from already interpolated ones), so the result does
  not depend on the order in which bad pixels are visited.

Why not what pizza-cutter / descwl_coadd do: pizza-cutter's ``interpolate_image_at_mask``
(``pizza_cutter/slice_utils/interpolate.py``; ``descwl_coadd/interp.py`` is a copy of it)
collects the good pixels within ``buff=4`` px of any bad pixel, Delaunay-triangulates them and
evaluates scipy's ``CloughTocher2DInterpolator`` (piecewise cubic, C1) at the bad pixels, with
0 outside the convex hull of the good pixels, and gives up when more than 90 % of the
pixels are bad; it is called separately on the image and on the noise image. That needs
scipy (not allowed in these kernels), its gradient estimation is an iterative global solve
with a tolerance (so the map from values to interpolated values is linear only to that
tolerance, and not evaluated once for all planes), and the triangulation of a regular
pixel grid is degenerate (four cocircular points per square) so the result depends on
tie-breaking. The plane fit keeps what matters from it (smooth, uses the good pixels on
every side of a hole, reproduces constants and gradients), with explicit weights. A
quadratic fit would also follow curvature, but needs more good pixels, has a larger
noise variance (``sum w^2``) and extrapolates badly into holes; curvature on the scale of a
bad pixel (a star's peak) is not recoverable anyway, and such pixels are recorded in
``mfrac``.

Windows and large holes
-----------------------
The first window has half-width ``r0 = max(1, ceil(3 sigma))`` (a ``(2 r0 + 1)^2`` box centred
on the bad pixel, clipped to the image) and Gaussian width ``s = sigma``. When it holds no
good pixel, or the plane is ill-determined, the half-width doubles (``r0, 2 r0, 4 r0, ...``,
capped at ``max_radius``) with ``s = sigma * r / r0``, so the window always spans
``3 s``. The plane is used when its extrapolation leverage ``h = m^T C^-1 m`` is at most
``max_leverage``, where ``m`` is the weighted centroid of the good pixels relative to the bad
pixel and ``C`` their weighted covariance; ``1 + h`` bounds the noise amplification over a
weighted mean of the same pixels (exactly ``(1 + h) / n`` for ``n`` equal weights). At
``max_radius`` an ill-determined plane falls back to the Gaussian-weighted mean (constants
still exact; for a gradient ``|grad f|`` the error is at most ``|grad f| * sqrt(2) *
max_radius``). A bad pixel with no good pixel within ``max_radius`` (Chebyshev distance) is
set to 0 in every plane and reported.

Noise
-----
For white noise of variance ``sigma_n^2`` in the good pixels, the interpolated value has
variance ``sigma_n^2 * sum_i w_i^2`` (:func:`interpolation_variance_ratio` returns the ratio
per pixel). For an isolated bad pixel far from the image edge and the defaults
(``sigma = 1``, window 7 x 7) the ratio is :data:`ISOLATED_VARIANCE_RATIO` = 0.076849 (the
interpolated value has about 13 times less variance than a good pixel, and is correlated
with its neighbours). The *variance plane*, interpolated with the same weights, gives the
local variance level (a weighted mean of the neighbours' variances), not that variance.

Conventions: ``pixels[y, x, p]`` (interleaved planes, C order), pixel centres at integer
coordinates, windows ``[y - r, y + r + 1) x [x - r, x + r + 1)`` (half-open), distances in
pixels.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from cellcoadd.errors import CellCoaddRangeError, CellCoaddValueError

DEFAULT_SIGMA = 1.0
"""Default Gaussian width of the interpolation weights (pixels)."""

DEFAULT_MAX_RADIUS = 32
"""Default largest window half-width (pixels)."""

DEFAULT_MAX_LEVERAGE = 4.0
"""Default largest extrapolation leverage ``h`` for which the plane fit is used."""

ISOLATED_VARIANCE_RATIO = 0.076849
"""``sum w^2`` for an isolated bad pixel with the default settings (white noise)."""

# A plane is ill-determined when det(C) <= _DEGENERATE * trace(C)^2 (good pixels on a line).
_DEGENERATE = 1e-9


@numba.njit(cache=True)
def window_radii(sigma: float, max_radius: int) -> np.ndarray:
    """Half-widths of the successive windows: ``r0, 2 r0, 4 r0, ...``, the last one
    ``max_radius``, with ``r0 = min(max(1, ceil(3 sigma)), max_radius)`` (pixels)."""
    r0 = min(max(1, math.ceil(3.0 * sigma)), max_radius)
    n = 1
    r = r0
    while r < max_radius:
        r = min(2 * r, max_radius)
        n += 1
    radii = np.empty(n, dtype=np.int64)
    r = r0
    for k in range(n):
        radii[k] = r
        r = min(2 * r, max_radius)
    return radii


@numba.njit(cache=True)
def good_count_table(bad: np.ndarray) -> np.ndarray:
    """Summed-area table of good pixels: ``t[j, i]`` = number of good pixels in
    ``[0, j) x [0, i)``, shape ``(ny + 1, nx + 1)``."""
    ny, nx = bad.shape
    table = np.zeros((ny + 1, nx + 1), dtype=np.int32)
    for y in range(ny):
        row = np.int32(0)
        above = table[y]
        below = table[y + 1]
        flags = bad[y]
        for x in range(nx):
            row += np.int32(1) - np.int32(flags[x])
            below[x + 1] = above[x + 1] + row
    return table


@numba.njit(cache=True)
def fill_bad_pixels(
    pixels: np.ndarray,
    bad: np.ndarray,
    sigma: float,
    max_radius: int,
    max_leverage: float,
    ratio: np.ndarray,
) -> np.ndarray:
    """Kernel of :func:`interpolate_bad_pixels`: replace the bad pixels of every plane in
    place, write ``sum w^2`` of every bad pixel to ``ratio`` (good pixels untouched) and
    return the bool map of bad pixels left at 0. ``pixels`` may have zero planes (then only
    ``ratio`` is computed). Inputs are validated by the callers."""
    ny, nx, n_planes = pixels.shape
    unfilled = np.zeros((ny, nx), dtype=np.bool_)
    radii = window_radii(sigma, max_radius)
    n_levels = radii.shape[0]
    r0 = radii[0]
    # Separable Gaussian factors of each level, indexed by offset + r.
    gauss = np.zeros((n_levels, 2 * max_radius + 1))
    for k in range(n_levels):
        r = radii[k]
        s = sigma * r / r0
        for d in range(-r, r + 1):
            gauss[k, d + r] = math.exp(-0.5 * (d / s) ** 2)
    counts = good_count_table(bad)
    acc = np.zeros(n_planes)

    for y in range(ny):
        for x in range(nx):
            if not bad[y, x]:
                continue
            level = -1
            mx = 0.0
            my = 0.0
            ax = 0.0
            ay = 0.0
            for k in range(n_levels):
                r = radii[k]
                y0 = max(0, y - r)
                y1 = min(ny, y + r + 1)
                x0 = max(0, x - r)
                x1 = min(nx, x + r + 1)
                n_good = counts[y1, x1] - counts[y0, x1] - counts[y1, x0] + counts[y0, x0]
                if n_good == 0:
                    continue
                # Weighted moments of the good pixels' offsets.
                s0 = 0.0
                sx = 0.0
                sy = 0.0
                sxx = 0.0
                sxy = 0.0
                syy = 0.0
                for yy in range(y0, y1):
                    dy = float(yy - y)
                    gy = gauss[k, yy - y + r]
                    for xx in range(x0, x1):
                        if bad[yy, xx]:
                            continue
                        dx = float(xx - x)
                        g = gy * gauss[k, xx - x + r]
                        s0 += g
                        sx += g * dx
                        sy += g * dy
                        sxx += g * dx * dx
                        sxy += g * dx * dy
                        syy += g * dy * dy
                mx = sx / s0
                my = sy / s0
                cxx = sxx / s0 - mx * mx
                cxy = sxy / s0 - mx * my
                cyy = syy / s0 - my * my
                det = cxx * cyy - cxy * cxy
                trace = cxx + cyy
                plane = False
                if trace > 0.0 and det > _DEGENERATE * trace * trace:
                    # a = C^-1 m; leverage h = m^T C^-1 m.
                    ax = (cyy * mx - cxy * my) / det
                    ay = (cxx * my - cxy * mx) / det
                    plane = mx * ax + my * ay <= max_leverage
                if plane:
                    level = k
                    break
                if k == n_levels - 1:
                    # Plane ill-determined even in the largest window: weighted mean.
                    ax = 0.0
                    ay = 0.0
                    level = k
            if level < 0:
                unfilled[y, x] = True
                ratio[y, x] = 0.0
                for p in range(n_planes):
                    pixels[y, x, p] = 0.0
                continue
            # w_i = g_i (1 - (d_i - m) . C^-1 m), normalised to sum 1.
            r = radii[level]
            y0 = max(0, y - r)
            y1 = min(ny, y + r + 1)
            x0 = max(0, x - r)
            x1 = min(nx, x + r + 1)
            acc[:] = 0.0
            w_sum = 0.0
            w2_sum = 0.0
            for yy in range(y0, y1):
                dy = float(yy - y)
                gy = gauss[level, yy - y + r]
                for xx in range(x0, x1):
                    if bad[yy, xx]:
                        continue
                    dx = float(xx - x)
                    w = gy * gauss[level, xx - x + r] * (1.0 - (dx - mx) * ax - (dy - my) * ay)
                    w_sum += w
                    w2_sum += w * w
                    for p in range(n_planes):
                        acc[p] += w * pixels[yy, xx, p]
            for p in range(n_planes):
                pixels[y, x, p] = acc[p] / w_sum
            ratio[y, x] = w2_sum / (w_sum * w_sum)
    return unfilled


def check_arguments(bad: np.ndarray, sigma: float, max_radius: int, max_leverage: float) -> None:
    """Raise ``ValueError`` unless ``bad`` is a 2-D bool array and the settings are valid."""
    if not isinstance(bad, np.ndarray) or bad.ndim != 2 or bad.dtype != np.bool_:
        raise CellCoaddValueError("bad must be a 2-D bool array")
    if not (math.isfinite(sigma) and sigma > 0):
        raise CellCoaddValueError(f"sigma must be finite and positive, got {sigma}", value=sigma)
    if int(max_radius) != max_radius or max_radius < 1:
        raise CellCoaddRangeError(
            f"max_radius must be an integer >= 1, got {max_radius}", value=max_radius, low=1
        )
    if not max_leverage >= 0:
        raise CellCoaddRangeError(
            f"max_leverage must be >= 0, got {max_leverage}", value=max_leverage, low=0
        )


def interpolate_bad_pixels(
    pixels: np.ndarray,
    bad: np.ndarray,
    *,
    sigma: float = DEFAULT_SIGMA,
    max_radius: int = DEFAULT_MAX_RADIUS,
    max_leverage: float = DEFAULT_MAX_LEVERAGE,
) -> np.ndarray:
    """Replace, in place, every bad pixel of every plane by the same linear combination of
    the good pixels around it (Gaussian-weighted local plane fit; see the module docstring).

    Parameters
    ----------
    pixels : ndarray, shape (ny, nx, P), float64, C-contiguous
        Interleaved planes ``pixels[y, x, p]`` (image, noise realizations, variance, ...).
        Modified in place at the bad pixels only; good pixels are not touched. The values
        of bad pixels on input are never read (they may be NaN).
    bad : ndarray, shape (ny, nx), bool
        True for the pixels to interpolate.
    sigma : float, optional
        Gaussian width of the weights in the first window (pixels); the first window's
        half-width is ``ceil(3 sigma)``. Default 1.
    max_radius : int, optional
        Largest window half-width (pixels); windows double up to it when the smaller ones
        hold no good pixel or an ill-determined plane. Default 32.
    max_leverage : float, optional
        Largest extrapolation leverage ``h`` for which the plane fit is used (else a larger
        window, and at ``max_radius`` the Gaussian-weighted mean). Default 4.

    Returns
    -------
    ndarray, shape (ny, nx), bool
        The bad pixels with no good pixel within ``max_radius`` (Chebyshev distance); they
        are set to 0 in every plane.

    Notes
    -----
    For white noise the interpolated value's variance is ``sum w^2`` times that of a good
    pixel (:func:`interpolation_variance_ratio`); :data:`ISOLATED_VARIANCE_RATIO` = 0.076849
    for an isolated bad pixel with the defaults.
    """
    check_arguments(bad, sigma, max_radius, max_leverage)
    if (
        not isinstance(pixels, np.ndarray)
        or pixels.ndim != 3
        or pixels.dtype != np.float64
        or not pixels.flags.c_contiguous
        or not pixels.flags.writeable
    ):
        raise CellCoaddValueError(
            "pixels must be a writeable C-contiguous float64 array (ny, nx, P)"
        )
    if pixels.shape[:2] != bad.shape:
        raise CellCoaddValueError(f"pixels {pixels.shape} and bad {bad.shape} disagree")
    if not bad.any():
        return np.zeros(bad.shape, dtype=bool)
    ratio = np.ones(bad.shape)
    return fill_bad_pixels(pixels, bad, float(sigma), int(max_radius), float(max_leverage), ratio)


def interpolation_variance_ratio(
    bad: np.ndarray,
    *,
    sigma: float = DEFAULT_SIGMA,
    max_radius: int = DEFAULT_MAX_RADIUS,
    max_leverage: float = DEFAULT_MAX_LEVERAGE,
) -> np.ndarray:
    """Variance of each pixel after :func:`interpolate_bad_pixels`, in units of a good
    pixel's variance, for white noise (uncorrelated, equal variance in the good pixels).

    Parameters
    ----------
    bad : ndarray, shape (ny, nx), bool
        The mask given to :func:`interpolate_bad_pixels`.
    sigma, max_radius, max_leverage
        As for :func:`interpolate_bad_pixels` (same defaults).

    Returns
    -------
    ndarray, shape (ny, nx), float64
        1 at good pixels, ``sum_i w_i^2`` at interpolated bad pixels (the weights sum to 1),
        0 at bad pixels that could not be interpolated (set to 0).
        :data:`ISOLATED_VARIANCE_RATIO` = 0.076849 for an isolated bad pixel at least
        3 px from the image edge with the defaults.
    """
    check_arguments(bad, sigma, max_radius, max_leverage)
    ratio = np.ones(bad.shape)
    if bad.any():
        no_planes = np.empty(bad.shape + (0,))
        fill_bad_pixels(no_planes, bad, float(sigma), int(max_radius), float(max_leverage), ratio)
    return ratio
