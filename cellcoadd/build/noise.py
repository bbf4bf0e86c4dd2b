"""Noise realizations generated on an exposure's own pixel grid.

The field of realization ``r`` of exposure ``(visit, detector)`` is a fixed function of
``(seed, visit, detector, r)`` and the pixel position: the exposure grid is cut into
``TILE`` x ``TILE`` tiles and each tile draws its standard normals from a generator keyed
by ``(seed, visit, detector, r, tile_x, tile_y)``. Any box of the field can be produced
without the rest, and two cells that use the same exposure see identical noise where
their footprints overlap, whatever order or process builds them.

A generator fills its tile row by row, so the first ``r`` rows of a tile come out the
same whether 64 or ``r`` rows are drawn. A caller that knows which pixels it will read
(:func:`tile_rows_read`) can therefore skip tiles it does not touch and stop drawing a
tile after the last row it needs; the pixels it reads are unchanged.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from cellcoadd.build.warp import KERNEL_HALF_WIDTH
from cellcoadd.geometry.box import Box

TILE = 64
_WORD_MASK = 0xFFFFFFFF


def _entropy_words(value: int) -> list[int]:
    """32-bit words of a non-negative integer, least significant first (``[0]`` for 0).

    ``numpy.random.SeedSequence`` reads every integer of its entropy this way, so keying
    it with the concatenated words gives the same generator as keying it with the integers;
    handing it a ready uint32 array skips its per-integer conversion (about a sixth of
    the cost of drawing a whole tile).
    """
    if value < 0:
        raise ValueError(f"noise generator keys must be non-negative, got {value}")
    if value == 0:
        return [0]
    words = []
    while value > 0:
        words.append(value & _WORD_MASK)
        value >>= 32
    return words


def _tile_normals(key_words: list[int], n_rows: int) -> np.ndarray:
    """The first ``n_rows`` rows of the tile keyed by ``key_words``."""
    entropy = np.array(key_words, dtype=np.uint32)
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(entropy)))
    return rng.standard_normal((n_rows, TILE))


_GROUP = 8  # output pixels per side of the groups whose taps are bounded together


@numba.njit(cache=True)
def _last_rows_read(
    x: np.ndarray, y: np.ndarray, first_tx: int, first_ty: int, last_rows: np.ndarray
) -> None:
    """Largest row index read in each tile by the kernel taps at the positions ``(x, y)``.

    The taps of each group of ``_GROUP`` x ``_GROUP`` positions are bounded by one box, so
    this may count a few rows too many (drawn for nothing) but never too few.
    """
    n_rows, n_cols = x.shape
    for row0 in range(0, n_rows, _GROUP):
        for col0 in range(0, n_cols, _GROUP):
            x_min = y_min = math.inf
            x_max = y_max = -math.inf
            for row in range(row0, min(row0 + _GROUP, n_rows)):
                for col in range(col0, min(col0 + _GROUP, n_cols)):
                    x_min = min(x_min, x[row, col])
                    x_max = max(x_max, x[row, col])
                    y_min = min(y_min, y[row, col])
                    y_max = max(y_max, y[row, col])
            x_lo = int(math.floor(x_min)) - (KERNEL_HALF_WIDTH - 1)
            x_hi = int(math.floor(x_max)) + KERNEL_HALF_WIDTH
            y_lo = int(math.floor(y_min)) - (KERNEL_HALF_WIDTH - 1)
            y_hi = int(math.floor(y_max)) + KERNEL_HALF_WIDTH
            for ty in range(y_lo // TILE, y_hi // TILE + 1):
                last = min(y_hi, (ty + 1) * TILE - 1)
                for tx in range(x_lo // TILE, x_hi // TILE + 1):
                    j, i = ty - first_ty, tx - first_tx
                    if last > last_rows[j, i]:
                        last_rows[j, i] = last


def tile_rows_read(x: np.ndarray, y: np.ndarray, box: Box) -> np.ndarray:
    """How many rows of each tile over ``box`` the resampling kernel reads, from the top.

    Parameters
    ----------
    x, y : ndarray, shape (ny, nx), float64
        Exposure pixel positions resampled with the Lanczos-3 taps
        ``floor(.) - 2 .. floor(.) + 3``; all their taps must lie in ``box``.
    box : Box
        Exposure pixels of the field (non-negative starts).

    Returns
    -------
    ndarray of int64, shape (n_tiles_y, n_tiles_x)
        Entry ``[j, i]`` is for the tile ``(box.x_start // TILE + i, box.y_start // TILE
        + j)``: one past its last row read, counted from the tile's first row (0: unread).
        Rows are bounded per small group of positions, so a few more may be counted than
        are read, never fewer.
    """
    first_tx, first_ty = box.x_start // TILE, box.y_start // TILE
    shape = ((box.y_stop - 1) // TILE + 1 - first_ty, (box.x_stop - 1) // TILE + 1 - first_tx)
    last_rows = np.full(shape, -1, dtype=np.int64)
    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    if x.size:
        _last_rows_read(x, y, first_tx, first_ty, last_rows)
    tile_tops = TILE * (first_ty + np.arange(shape[0]))[:, np.newaxis]
    return np.where(last_rows >= 0, last_rows - tile_tops + 1, 0)


def standard_normal_field(
    seed: int,
    visit: int,
    detector: int,
    realization: int,
    box: Box,
    rows_read: np.ndarray | None = None,
) -> np.ndarray:
    """Unit-variance Gaussian noise over ``box`` (exposure pixels, starting at >= 0).

    Parameters
    ----------
    seed, visit, detector, realization : int
        Non-negative key of the field.
    box : Box
        Exposure pixels wanted.
    rows_read : ndarray of int, optional
        From :func:`tile_rows_read`: only these rows of each tile are drawn and the other
        pixels are set to zero. Default: the whole box.

    Returns
    -------
    ndarray
        Float64 array of ``box.shape``.
    """
    if box.x_start < 0 or box.y_start < 0:
        raise ValueError(f"noise boxes live on the exposure grid (>= 0), got {box}")
    for name, value in (("seed", seed), ("visit", visit), ("detector", detector)):
        if value < 0:
            raise ValueError(f"{name} must be non-negative to key the noise generator: {value}")
    prefix = []
    for value in (seed, visit, detector, realization):
        prefix += _entropy_words(int(value))
    out = (np.zeros if rows_read is not None else np.empty)(box.shape, dtype=np.float64)
    first_tx, first_ty = box.x_start // TILE, box.y_start // TILE
    for ty in range(first_ty, (box.y_stop - 1) // TILE + 1):
        top = ty * TILE
        y_lo, y_hi = max(box.y_start, top), min(box.y_stop, top + TILE)  # rows in the box
        for tx in range(first_tx, (box.x_stop - 1) // TILE + 1):
            left = tx * TILE
            x_lo, x_hi = max(box.x_start, left), min(box.x_stop, left + TILE)
            n_rows = y_hi - top
            if rows_read is not None:
                n_rows = min(n_rows, int(rows_read[ty - first_ty, tx - first_tx]))
            if n_rows <= y_lo - top or x_lo >= x_hi:
                continue  # nothing of this tile is wanted
            tile = _tile_normals(prefix + _entropy_words(tx) + _entropy_words(ty), n_rows)
            out[
                y_lo - box.y_start : top + n_rows - box.y_start,
                x_lo - box.x_start : x_hi - box.x_start,
            ] = tile[y_lo - top :, x_lo - left : x_hi - left]
    return out
