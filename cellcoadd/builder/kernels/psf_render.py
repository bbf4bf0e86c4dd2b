"""Rendering an oversampled PSF core onto a coadd PSF stamp: a source at a given exposure
phase, resampled through a local affine map with the image's normalised Lanczos-3
weights (:func:`~cellcoadd.builder.kernels.lanczos.lanczos_taps`).

:func:`render_cores` is what :func:`cellcoadd.builder.psf.render_cores` runs: the core's
cubic B-spline (coefficients beyond the core mirrored, as scipy does) sampled at the exposure
pixels around the source, normalised to unit sum, tapered to zero over its last
``taper`` pixels, then warped; only the stamp pixels whose taps reach the core are
computed (a core of +-8 exposure pixels covers ~30 x 30 pixels of a 75-pixel stamp).
The arithmetic is that of :func:`cellcoadd.model.psf_phase.render_input` (which
``CellCoadd.psf_at`` runs) up to rounding.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from cellcoadd.builder.kernels.lanczos import lanczos_taps

#: Padding, pixels, around the sampled core so the 6 x 6 taps need no bounds checks.
_PAD = 6


@numba.njit(cache=True, inline="always")
def _bspline(s: float) -> tuple[float, float, float, float]:
    """Cubic B-spline weights of the taps ``floor(t) - 1`` to ``floor(t) + 2``, at
    ``s = t - floor(t)``."""
    r = 1.0 - s
    s2 = s * s
    s3 = s2 * s
    return (
        r * r * r / 6.0,
        (3.0 * s3 - 6.0 * s2 + 4.0) / 6.0,
        (-3.0 * s3 + 3.0 * s2 + 3.0 * s + 1.0) / 6.0,
        s3 / 6.0,
    )


@numba.njit(cache=True, inline="always")
def _mirror(index: int, m: int) -> int:
    """A coefficient index beyond the core reflected about its edge sample (scipy's spline
    evaluation at the edges of ``map_coordinates``)."""
    if index < 0:
        return -index
    if index >= m:
        return 2 * (m - 1) - index
    return index


@numba.njit(cache=True)
def _sample(
    coefficients: np.ndarray, fx: float, fy: float, half: int, oversampling: int, taper: float
) -> np.ndarray:
    """The core at the exposure pixels ``-half`` to ``half`` around a source at phase
    ``(fx, fy)``, unit sum, tapered, inside a zero border of :data:`_PAD` pixels."""
    m = coefficients.shape[0]
    centre = (m - 1) / 2.0
    side = 2 * half + 1
    padded = np.zeros((side + 2 * _PAD, side + 2 * _PAD))
    total = 0.0
    for j in range(side):
        ty = (j - half - fy) * oversampling + centre
        if ty < 0.0 or ty > m - 1.0:
            continue
        by = math.floor(ty)
        v0, v1, v2, v3 = _bspline(ty - by)
        for i in range(side):
            tx = (i - half - fx) * oversampling + centre
            if tx < 0.0 or tx > m - 1.0:
                continue
            bx = math.floor(tx)
            u0, u1, u2, u3 = _bspline(tx - bx)
            value = 0.0
            for b in range(4):
                row = _mirror(int(by) - 1 + b, m)
                wy = v0 if b == 0 else (v1 if b == 1 else (v2 if b == 2 else v3))
                line = 0.0
                for a in range(4):
                    col = _mirror(int(bx) - 1 + a, m)
                    wx = u0 if a == 0 else (u1 if a == 1 else (u2 if a == 2 else u3))
                    line += wx * coefficients[row, col]
                value += wy * line
            padded[_PAD + j, _PAD + i] = value
            total += value
    scale = 1.0 / total if total > 0.0 else 1.0
    for j in range(side):
        for i in range(side):
            distance = max(abs(i - half - fx), abs(j - half - fy))
            ramp = min(max((half - distance) / taper, 0.0), 1.0)
            padded[_PAD + j, _PAD + i] *= scale * (0.5 - 0.5 * math.cos(math.pi * ramp))
    return padded


# numpy error model: an integral offset divides 0 by 0 in lanczos_taps, which selects it away
@numba.njit(cache=True, error_model="numpy", fastmath={"contract", "reassoc"})
def render_cores(
    coefficients: np.ndarray,
    phases: np.ndarray,
    jacobians: np.ndarray,
    areas: np.ndarray,
    half: int,
    oversampling: int,
    taper: float,
    out: np.ndarray,
) -> None:
    """``out[p]`` (zeroed, ``(P, n, n)``, odd ``n``) = ``areas[p]`` times the core of cubic
    B-spline ``coefficients[p]`` (``oversampling`` samples per exposure pixel, centred) for
    a source at exposure phase ``phases[p]``, sampled over ``-half`` to ``half`` exposure
    pixels, normalised, tapered over ``taper`` pixels, resampled at the exposure offsets
    ``phases[p] + jacobians[p] @ (i - n // 2, j - n // 2)`` of stamp pixel ``(i, j)``."""
    size = out.shape[1]
    centre = size // 2
    reach = half + 3.0
    for p in range(out.shape[0]):
        fx, fy = phases[p, 0], phases[p, 1]
        padded = _sample(coefficients[p], fx, fy, half, oversampling, taper)
        a00, a01 = jacobians[p, 0, 0], jacobians[p, 0, 1]
        a10, a11 = jacobians[p, 1, 0], jacobians[p, 1, 1]
        # the stamp pixels that may reach the core: the box around the parallelogram
        # jacobian^-1 ([-reach, reach]^2 - phase)
        det = a00 * a11 - a01 * a10
        b00, b01, b10, b11 = a11 / det, -a01 / det, -a10 / det, a00 / det
        extent_x = (abs(b00) + abs(b01)) * (reach + 1.0)
        extent_y = (abs(b10) + abs(b11)) * (reach + 1.0)
        i_lo = max(0, int(math.floor(centre - extent_x)))
        i_hi = min(size, int(math.ceil(centre + extent_x)) + 1)
        j_lo = max(0, int(math.floor(centre - extent_y)))
        j_hi = min(size, int(math.ceil(centre + extent_y)) + 1)
        stamp = out[p]
        area = areas[p]
        for j in range(j_lo, j_hi):
            dy = float(j - centre)
            for i in range(i_lo, i_hi):
                dx = float(i - centre)
                ux = fx + a00 * dx + a01 * dy
                uy = fy + a10 * dx + a11 * dy
                if abs(ux) >= reach or abs(uy) >= reach:
                    continue
                x0, x1, x2, x3, x4, x5, floor_x, _ = lanczos_taps(ux)
                y0, y1, y2, y3, y4, y5, floor_y, _ = lanczos_taps(uy)
                col = int(floor_x) - 2 + half + _PAD
                row = int(floor_y) - 2 + half + _PAD
                total = (
                    y0 * _dot6(padded[row], col, x0, x1, x2, x3, x4, x5)
                    + y1 * _dot6(padded[row + 1], col, x0, x1, x2, x3, x4, x5)
                    + y2 * _dot6(padded[row + 2], col, x0, x1, x2, x3, x4, x5)
                    + y3 * _dot6(padded[row + 3], col, x0, x1, x2, x3, x4, x5)
                    + y4 * _dot6(padded[row + 4], col, x0, x1, x2, x3, x4, x5)
                    + y5 * _dot6(padded[row + 5], col, x0, x1, x2, x3, x4, x5)
                )
                stamp[j, i] = area * total


@numba.njit(cache=True, inline="always")
def _dot6(
    line: np.ndarray, col: int, x0: float, x1: float, x2: float, x3: float, x4: float, x5: float
) -> float:
    return (
        x0 * line[col]
        + x1 * line[col + 1]
        + x2 * line[col + 2]
        + x3 * line[col + 3]
        + x4 * line[col + 4]
        + x5 * line[col + 5]
    )


__all__ = ["render_cores"]
