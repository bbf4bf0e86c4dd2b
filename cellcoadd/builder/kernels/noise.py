"""Noise realizations as a fixed function of the exposure pixel: a counter-based generator.

Realization ``r`` of exposure ``(visit, detector)`` built with ``seed`` has, at exposure
pixel ``(x, y)``, a standard normal computed from Philox4x32-10 blocks (Salmon et al.
2011, "Parallel random numbers: as easy as 1, 2, 3"; the generator of numpy's ``Philox``
and of the Random123 library):

* key: two 32-bit words derived from ``(seed, visit, detector)`` by
  ``numpy.random.SeedSequence`` (:func:`noise_key`);
* counter: ``(x, y, r // 2, attempt)``; the first 64 bits of a block serve even ``r``,
  the last 64 odd ``r``;
* normal: the ziggurat method of Marsaglia & Tsang (2000, J. Stat. Softw. 5, 8) with 256
  layers. A 64-bit word gives the layer (8 bits), the sign (1 bit) and a 53-bit uniform
  (bits that do not overlap, Doornik 2005); about 99% of the words are accepted at once,
  the others take one more block for the wedge test (counter ``2 * attempt + 1``) or
  retry with the next ``attempt``. The tail beyond the base layer is sampled by
  inverting the normal CDF (Wichura 1988, AS241 ``PPND16``, :func:`ndtri`).

Any pixel of any realization is computed on its own, so a builder computes exactly the
pixels it reads, overlapping cells see identical noise wherever their footprints overlap,
and no result depends on the order or the process in which cells are built. numpy's own
generators are sequential streams; random access by pixel is what needs a counter-based
generator here.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from cellcoadd.errors import CellCoaddRangeError, CellCoaddValueError
from cellcoadd.geometry.box import Box

_MASK32 = np.uint64(0xFFFFFFFF)
_SHIFT32 = np.uint64(32)
_SHIFT11 = np.uint64(11)
# Philox4x32 round multipliers and key increments (Weyl constants) of Random123.
_PHILOX_M0 = np.uint64(0xD2511F53)
_PHILOX_M1 = np.uint64(0xCD9E8D57)
_PHILOX_W0 = np.uint64(0x9E3779B9)
_PHILOX_W1 = np.uint64(0xBB67AE85)
_PHILOX_ROUNDS = 10
_TWO_TO_MINUS_53 = 2.0**-53
_LAYER_BITS = np.uint64(0xFF)
_SIGN_SHIFT = np.uint64(8)
_ONE = np.uint64(1)


def _ziggurat_edges() -> np.ndarray:
    """Right edges ``x[i]`` of the 256 ziggurat layers of ``exp(-x^2 / 2)``, ``x[256] = 0``.

    Layer ``i >= 1`` is the rectangle ``[0, x[i]] x [f(x[i]), f(x[i + 1])]``; the base
    layer 0 has width ``x[0] = v / f(r)`` so that its part beyond ``r = x[1]`` has the
    area of the tail. Every layer has the area ``v`` (Marsaglia & Tsang 2000).
    """
    base_edge, area = 3.6541528853610088, 0.00492867323399
    edges = np.zeros(257)
    edges[0], edges[1] = area / math.exp(-0.5 * base_edge**2), base_edge
    for i in range(2, 256):
        edges[i] = math.sqrt(
            -2.0 * math.log(area / edges[i - 1] + math.exp(-0.5 * edges[i - 1] ** 2))
        )
    return edges


_EDGES = _ziggurat_edges()
_HEIGHTS = np.exp(-0.5 * _EDGES**2)
# P(z > x[1]) for a standard normal: the tail is sampled by inverting the CDF below it
_TAIL_PROBABILITY = 0.5 * math.erfc(_EDGES[1] / math.sqrt(2.0))


@numba.njit(cache=True, inline="always")
def philox4x32(
    c0: np.uint64,
    c1: np.uint64,
    c2: np.uint64,
    c3: np.uint64,
    k0: np.uint64,
    k1: np.uint64,
) -> tuple[np.uint64, np.uint64, np.uint64, np.uint64]:
    """Philox4x32-10 block of the counter ``(c0, c1, c2, c3)`` under the key ``(k0, k1)``.

    Every argument and result is a 32-bit word held in a uint64.
    """
    for round_index in range(_PHILOX_ROUNDS):
        if round_index > 0:
            k0 = (k0 + _PHILOX_W0) & _MASK32
            k1 = (k1 + _PHILOX_W1) & _MASK32
        product0 = _PHILOX_M0 * c0
        product1 = _PHILOX_M1 * c2
        c0, c1, c2, c3 = (
            (product1 >> _SHIFT32) ^ c1 ^ k0,
            product1 & _MASK32,
            (product0 >> _SHIFT32) ^ c3 ^ k1,
            product0 & _MASK32,
        )
    return c0, c1, c2, c3


@numba.njit(cache=True)
def ndtri(p: float) -> float:
    """Inverse of the standard normal CDF at ``p`` in (0, 1) (AS241 ``PPND16``)."""
    q = p - 0.5
    if abs(q) <= 0.425:
        r = 0.180625 - q * q
        numerator = (
            ((((((2509.0809287301226727 * r + 33430.575583588128105) * r
            + 67265.770927008700853) * r + 45921.953931549871457) * r
            + 13731.693765509461125) * r + 1971.5909503065514427) * r
            + 133.14166789178437745) * r + 3.387132872796366608
        )  # fmt: skip
        denominator = (
            ((((((5226.495278852545925 * r + 28729.085735721942674) * r
            + 39307.89580009271061) * r + 21213.794301586595867) * r
            + 5394.1960214247511077) * r + 687.1870074920579083) * r
            + 42.313330701600911252) * r + 1.0
        )  # fmt: skip
        return q * numerator / denominator
    r = math.sqrt(-math.log(p if q < 0.0 else 1.0 - p))
    if r <= 5.0:
        r -= 1.6
        numerator = (
            ((((((7.7454501427834140764e-4 * r + 0.0227238449892691845833) * r
            + 0.24178072517745061177) * r + 1.27045825245236838258) * r
            + 3.64784832476320460504) * r + 5.7694972214606914055) * r
            + 4.6303378461565452959) * r + 1.42343711074968357734
        )  # fmt: skip
        denominator = (
            ((((((1.05075007164441684324e-9 * r + 5.475938084995344946e-4) * r
            + 0.0151986665636164571966) * r + 0.14810397642748007459) * r
            + 0.68976733498510000455) * r + 1.6763848301838038494) * r
            + 2.05319162663775882187) * r + 1.0
        )  # fmt: skip
    else:
        r -= 5.0
        numerator = (
            ((((((2.01033439929228813265e-7 * r + 2.71155556874348757815e-5) * r
            + 0.0012426609473880784386) * r + 0.026532189526576123093) * r
            + 0.29656057182850489123) * r + 1.7848265399172913358) * r
            + 5.4637849111641143699) * r + 6.6579046435011037772
        )  # fmt: skip
        denominator = (
            ((((((2.04426310338993978564e-15 * r + 1.4215117583164458887e-7) * r
            + 1.8463183175100546818e-5) * r + 7.868691311456132591e-4) * r
            + 0.0148753612908506148525) * r + 0.13692988092273580531) * r
            + 0.59983220655588793769) * r + 1.0
        )  # fmt: skip
    value = numerator / denominator
    return -value if q < 0.0 else value


@numba.njit(cache=True, inline="always")
def _half_word(
    x: int, y: int, pair: int, counter3: int, half: int, k0: np.uint64, k1: np.uint64
) -> np.uint64:
    """64 bits of the block ``(x, y, pair, counter3)``: its first half or its second."""
    w0, w1, w2, w3 = philox4x32(
        np.uint64(x), np.uint64(y), np.uint64(pair), np.uint64(counter3), k0, k1
    )
    if half == 0:
        return (w0 << _SHIFT32) | w1
    return (w2 << _SHIFT32) | w3


@numba.njit(cache=True, inline="always")
def _ziggurat_try(word: np.uint64) -> tuple[int, float, float]:
    """Layer, signed candidate and its magnitude from one 64-bit word."""
    layer = int(word & _LAYER_BITS)
    magnitude = ((word >> _SHIFT11) + 0.5) * _TWO_TO_MINUS_53 * _EDGES[layer]
    signed = -magnitude if (word >> _SIGN_SHIFT) & _ONE else magnitude
    return layer, signed, magnitude


@numba.njit(cache=True)
def _ziggurat_slow(
    word: np.uint64, x: int, y: int, realization: int, k0: np.uint64, k1: np.uint64
) -> float:
    """The normal of a word that fell outside its layer's inner rectangle (~1% of words)."""
    pair, half = realization // 2, realization % 2
    attempt = 0
    while True:
        layer, signed, magnitude = _ziggurat_try(word)
        if magnitude < _EDGES[layer + 1]:
            return signed
        extra = _half_word(x, y, pair, 2 * attempt + 1, half, k0, k1)
        uniform = ((extra >> _SHIFT11) + 0.5) * _TWO_TO_MINUS_53
        if layer == 0:  # beyond the base layer: invert the CDF over the tail
            tail = -ndtri(uniform * _TAIL_PROBABILITY)
            return -tail if signed < 0.0 else tail
        height = _HEIGHTS[layer] + uniform * (_HEIGHTS[layer + 1] - _HEIGHTS[layer])
        if height < math.exp(-0.5 * magnitude * magnitude):
            return signed
        attempt += 1
        word = _half_word(x, y, pair, 2 * attempt, half, k0, k1)


@numba.njit(cache=True, inline="always")
def normal_from_word(
    word: np.uint64, x: int, y: int, realization: int, k0: np.uint64, k1: np.uint64
) -> float:
    """The unit normal of realization ``realization`` at ``(x, y)``, given its first word
    (from :func:`first_words`)."""
    layer, signed, magnitude = _ziggurat_try(word)
    if magnitude < _EDGES[layer + 1]:
        return signed
    return _ziggurat_slow(word, x, y, realization, k0, k1)


@numba.njit(cache=True, inline="always")
def first_words(
    x_start: int, y: int, n_noise: int, k0: np.uint64, k1: np.uint64, words: np.ndarray
) -> None:
    """First words of realizations ``0`` to ``n_noise - 1`` at pixels ``x_start + i`` of row
    ``y``, into ``words[r, i]`` for ``i < words.shape[1]``.

    A plain loop over independent blocks, which the compiler vectorises: Philox is
    latency-bound one block at a time, about three times faster in batches.
    """
    for pair in range((n_noise + 1) // 2):
        for i in range(words.shape[1]):
            w0, w1, w2, w3 = philox4x32(
                np.uint64(x_start + i), np.uint64(y), np.uint64(pair), np.uint64(0), k0, k1
            )
            words[2 * pair, i] = (w0 << _SHIFT32) | w1
            if 2 * pair + 1 < n_noise:
                words[2 * pair + 1, i] = (w2 << _SHIFT32) | w3


@numba.njit(cache=True)
def _fill_normals(
    out: np.ndarray, x_start: int, y_start: int, realization: int, k0: np.uint64, k1: np.uint64
) -> None:
    words = np.empty((realization + 1, out.shape[1]), dtype=np.uint64)
    for row in range(out.shape[0]):
        first_words(x_start, y_start + row, realization + 1, k0, k1, words)
        for col in range(out.shape[1]):
            out[row, col] = normal_from_word(
                words[realization, col], x_start + col, y_start + row, realization, k0, k1
            )


def noise_key(seed: int, visit: int, detector: int) -> tuple[np.uint64, np.uint64]:
    """The generator key (two 32-bit words) of the noise of one exposure.

    Raises
    ------
    ValueError
        If any of the integers is negative.
    """
    for name, value in (("seed", seed), ("visit", visit), ("detector", detector)):
        if int(value) < 0:
            raise CellCoaddRangeError(
                f"{name} must be non-negative to key the noise generator: {value}",
                value=value,
                low=0,
            )
    words = np.random.SeedSequence([int(seed), int(visit), int(detector)]).generate_state(2)
    return np.uint64(words[0]), np.uint64(words[1])


def standard_normal_field(
    seed: int, visit: int, detector: int, realization: int, box: Box
) -> np.ndarray:
    """Realization ``realization`` of the unit-variance noise over ``box``.

    Parameters
    ----------
    seed, visit, detector, realization : int
        Non-negative key of the field.
    box : Box
        Exposure pixels wanted (0-based, pixel centres at integers; starts >= 0).

    Returns
    -------
    ndarray
        Float64 array of ``box.shape``; ``[j, i]`` is pixel ``(box.x_start + i,
        box.y_start + j)``, the same value whatever box it is asked in.
    """
    if box.x_start < 0 or box.y_start < 0:
        raise CellCoaddValueError(f"noise lives on the exposure grid (>= 0), got {box}", value=box)
    if realization < 0:
        raise CellCoaddRangeError(
            f"realization must be non-negative: {realization}", value=realization, low=0
        )
    k0, k1 = noise_key(seed, visit, detector)
    out = np.empty(box.shape)
    _fill_normals(out, box.x_start, box.y_start, int(realization), k0, k1)
    return out


__all__ = [
    "first_words",
    "ndtri",
    "noise_key",
    "normal_from_word",
    "philox4x32",
    "standard_normal_field",
]
