"""Noise realizations generated on an exposure's own pixel grid.

The field of realization ``r`` of exposure ``(visit, detector)`` is a fixed function of
``(seed, visit, detector, r)`` and the pixel position: the exposure grid is cut into
``TILE`` x ``TILE`` tiles and each tile draws its standard normals from a generator keyed
by ``(seed, visit, detector, r, tile_x, tile_y)``. Any box of the field can be produced
without the rest, and two cells that use the same exposure see identical noise where
their footprints overlap, whatever order or process builds them.
"""

from __future__ import annotations

import numpy as np

from cellcoadd.geometry.box import Box

TILE = 64


def _tile_normals(key: tuple[int, ...]) -> np.ndarray:
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(key)))
    return rng.standard_normal((TILE, TILE))


def standard_normal_field(
    seed: int, visit: int, detector: int, realization: int, box: Box
) -> np.ndarray:
    """Unit-variance Gaussian noise over ``box`` (exposure pixels, starting at >= 0).

    Returns a float64 array of ``box.shape``.
    """
    if box.x_start < 0 or box.y_start < 0:
        raise ValueError(f"noise boxes live on the exposure grid (>= 0), got {box}")
    for name, value in (("seed", seed), ("visit", visit), ("detector", detector)):
        if value < 0:
            raise ValueError(f"{name} must be non-negative to key the noise generator: {value}")
    out = np.empty(box.shape, dtype=np.float64)
    for ty in range(box.y_start // TILE, (box.y_stop - 1) // TILE + 1):
        for tx in range(box.x_start // TILE, (box.x_stop - 1) // TILE + 1):
            tile_box = Box(
                x_start=tx * TILE, x_stop=(tx + 1) * TILE, y_start=ty * TILE, y_stop=(ty + 1) * TILE
            )
            common = tile_box.intersection(box)
            tile = _tile_normals((seed, visit, detector, realization, tx, ty))
            out[common.slices_in(box)] = tile[common.slices_in(tile_box)]
    return out
