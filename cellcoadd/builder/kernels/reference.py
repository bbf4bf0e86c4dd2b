"""The warp written plainly: the definition the fast kernels are tested against, bit for bit.

For every output pixel mapped to input position ``(x, y)`` and every plane ``p``:

1. the normalised one-dimensional weights ``wx_0 .. wx_5`` of the taps
   ``floor(x) - 2 .. floor(x) + 3``, and likewise ``wy`` in y
   (:func:`~cellcoadd.builder.kernels.lanczos.lanczos_taps`, the one definition of the
   weights; they equal ``sinc(t) sinc(t / 3)`` divided by their sum to ~1e-16);
2. the column sums ``c_b = sum_a wy_a * v[a, b]`` over the rows ``a`` of the footprint,
   then ``s = sum_b wx_b * c_b``, each sum over taps taken in the order of :func:`tap_sum`,
   with separate multiplications and additions (no fused multiply-add);
3. when the position is integral in both axes the output copies the input pixel instead
   (bit for bit, and immune to non-finite neighbours);
4. ``out[p] += (plane_weights[p] * scales[plane_scales[p]]) * s``, or
   ``plane_weights[p] * s`` when ``plane_scales[p]`` is -1.

:func:`~cellcoadd.builder.kernels.accumulate.accumulate_warped` computes exactly this,
with weight tables, interleaved planes, explicit SIMD vectors and prefetching; this
module does it one pixel, one plane and one tap at a time. It is slow: a reference for
tests, not a route of the builder.

Conventions: 0-based input pixel coordinates with pixel centres at integers.
"""

from __future__ import annotations

import numba
import numpy as np

from cellcoadd.builder.kernels.descriptor import LANCZOS3
from cellcoadd.builder.kernels.lanczos import lanczos_taps

_TAPS = LANCZOS3.taps
_FIRST_OFFSET = LANCZOS3.first_offset


@numba.njit(cache=True)
def tap_sum(terms: np.ndarray) -> float:
    """The sum of ``terms`` (one per tap) in the kernels' order: adjacent pairs, round
    after round, an odd last term joining the next round; for six terms
    ``((t0 + t1) + (t2 + t3)) + (t4 + t5)``. ``terms`` is overwritten."""
    n = terms.shape[0]
    while n > 1:
        half = n // 2
        for k in range(half):
            terms[k] = terms[2 * k] + terms[2 * k + 1]
        if n % 2:
            terms[half] = terms[n - 1]
        n = half + n % 2
    return terms[0]


# numpy's error model: an integral position divides by zero in lanczos_taps (the selects
# there drop the result), as in the fast kernels' weight tables
@numba.njit(cache=True, error_model="numpy")
def _weights(position: float, weights: np.ndarray) -> tuple[int, int]:
    """Fill ``weights`` with the taps' weights of ``position``; return its first tap and
    the input pixel it coincides with (-1: none)."""
    w0, w1, w2, w3, w4, w5, floor_position, exact = lanczos_taps(position)
    weights[0], weights[1], weights[2] = w0, w1, w2
    weights[3], weights[4], weights[5] = w3, w4, w5
    return int(floor_position) + _FIRST_OFFSET, int(exact)


@numba.njit(cache=True)
def reference_accumulate(
    planes: np.ndarray,
    x_src: np.ndarray,
    y_src: np.ndarray,
    out: np.ndarray,
    plane_weights: np.ndarray,
    scales: np.ndarray,
    plane_scales: np.ndarray,
) -> None:
    """``out[p] += plane_weights[p] * scales[plane_scales[p]] * warp(planes[p])`` as the
    module notes define it.

    Parameters
    ----------
    planes : ndarray, shape (P, ny_in, nx_in), float64
        Input planes; every tap of every position must lie inside them.
    x_src, y_src : ndarray, shape (ny_out, nx_out), float64
        Input positions of the output pixel centres.
    out : ndarray, shape (P, ny_out, nx_out), float64
        Accumulator, updated in place.
    plane_weights : ndarray, shape (P,), float64
        Scalar weight of each plane.
    scales : ndarray, shape (S, ny_out, nx_out), float64
        Per-output-pixel factors (any shape when no plane uses one).
    plane_scales : ndarray, shape (P,), int64
        Index into ``scales`` of each plane's factor, -1 for none.
    """
    weights_x = np.empty(_TAPS)
    weights_y = np.empty(_TAPS)
    columns = np.empty(_TAPS)
    terms = np.empty(_TAPS)
    for row in range(x_src.shape[0]):
        for col in range(x_src.shape[1]):
            first_x, exact_x = _weights(x_src[row, col], weights_x)
            first_y, exact_y = _weights(y_src[row, col], weights_y)
            for p in range(planes.shape[0]):
                if exact_x >= 0 and exact_y >= 0:
                    value = planes[p, exact_y, exact_x]
                else:
                    for b in range(_TAPS):
                        for a in range(_TAPS):
                            terms[a] = weights_y[a] * planes[p, first_y + a, first_x + b]
                        columns[b] = tap_sum(terms)
                    for b in range(_TAPS):
                        terms[b] = weights_x[b] * columns[b]
                    value = tap_sum(terms)
                which = plane_scales[p]
                if which >= 0:
                    out[p, row, col] += (plane_weights[p] * scales[which, row, col]) * value
                else:
                    out[p, row, col] += plane_weights[p] * value


__all__ = ["reference_accumulate", "tap_sum"]
