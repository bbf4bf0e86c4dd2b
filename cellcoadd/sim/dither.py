"""Dither patterns: per-visit pointing offsets and rotations.

Offsets are flat-sky ``(x, y)`` (or ``(du, dv)``) displacements of the optical axis from
the nominal field centre, arcsec. One function, :func:`dither_offsets`, serves both users:

* the field simulation (:mod:`cellcoadd.sim.field`) dithers inside a *disk*
  (``region="disk"``): ``"random"`` is uniform over the disk, ``"spiral"`` a Vogel
  (sunflower) spiral filling it evenly from a random starting angle;
* the edge-rejection statistics (:mod:`cellcoadd.analysis.rejection`, paper section 5.2,
  Fig. 5) dither inside a *hexagon* whose circumradius is about the focal-plane radius
  (``region="hexagon"``, the default): ``"random"`` draws offsets uniformly inside it,
  ``"spiral"`` walks an Archimedean spiral inside its inscribed circle.

``"none"`` gives zero offsets in either region.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from cellcoadd.errors import CellCoaddValueError

DitherPattern = Literal["random", "spiral", "none"]
DitherRegion = Literal["disk", "hexagon"]
RotationMode = Literal["random", "none"]

_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def in_hexagon(x: np.ndarray, y: np.ndarray, circumradius: float) -> np.ndarray:
    """Whether points are inside the regular hexagon with vertices at angles 0, 60, ... deg."""
    apothem = circumradius * np.sqrt(3.0) / 2.0
    ax, ay = np.abs(x), np.abs(y)
    return (ay <= apothem) & (np.sqrt(3.0) * ax + ay <= np.sqrt(3.0) * circumradius)


def hexagon_offsets(n: int, circumradius: float, rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniform inside a hexagon of the given circumradius, shape ``(n, 2)``.

    Rejection sampling from the bounding box (acceptance 3 sqrt(3) / 8 = 65 %).
    """
    points = np.empty((0, 2))
    apothem = circumradius * np.sqrt(3.0) / 2.0
    while points.shape[0] < n:
        draw = rng.uniform(-1.0, 1.0, size=(2 * n + 8, 2)) * [circumradius, apothem]
        points = np.vstack([points, draw[in_hexagon(draw[:, 0], draw[:, 1], circumradius)]])
    return points[:n]


def spiral_offsets(
    n_visits: int, max_radius: float, n_points: int = 60, n_coils: int = 6
) -> np.ndarray:
    """Offsets of an Archimedean spiral, cycled over visits, shape ``(n_visits, 2)``.

    ``n_points`` positions equally spaced in angle over ``n_coils`` turns, the radius growing
    linearly with angle up to ``max_radius``; visit ``k`` uses position ``k mod n_points``.
    """
    if n_points < 1 or n_coils < 1:
        raise CellCoaddValueError(
            "n_points and n_coils must be positive", value=(n_points, n_coils)
        )
    step = np.arange(1, n_points + 1) / n_points
    angle = 2.0 * np.pi * n_coils * step
    radius = max_radius * step
    pattern = np.column_stack([radius * np.cos(angle), radius * np.sin(angle)])
    return pattern[np.arange(n_visits) % n_points]


def disk_offsets(
    pattern: Literal["random", "spiral"], n_visits: int, radius: float, rng: np.random.Generator
) -> np.ndarray:
    """Offsets filling the disk of ``radius``, shape ``(n_visits, 2)``.

    ``"random"``: uniform over the disk, one pair of draws per visit (so the first visits do
    not depend on how many follow); ``"spiral"``: a Vogel (sunflower) spiral that fills the
    disk evenly, starting at a random angle.
    """
    r: np.ndarray
    phi: np.ndarray
    if pattern == "random":
        uniform = rng.uniform(size=(n_visits, 2))
        r = radius * np.sqrt(uniform[:, 0])
        phi = 2.0 * np.pi * uniform[:, 1]
    else:
        k = np.arange(n_visits)
        r = radius * np.sqrt((k + 0.5) / n_visits)
        phi = rng.uniform(0.0, 2.0 * np.pi) + k * _GOLDEN_ANGLE
    return np.column_stack([r * np.cos(phi), r * np.sin(phi)])


def dither_offsets(
    pattern: DitherPattern,
    n_visits: int,
    radius: float,
    rng: np.random.Generator,
    *,
    region: DitherRegion = "hexagon",
) -> np.ndarray:
    """Per-visit pointing offsets, arcsec, shape ``(n_visits, 2)``.

    Parameters
    ----------
    pattern : "random", "spiral" or "none"
        Uniform in the region, a spiral inside it, or zero offsets.
    n_visits : int
        Number of visits.
    radius : float
        Size of the region, arcsec: the hexagon's circumradius or the disk's radius.
    rng : numpy.random.Generator
        Random stream (unused by ``"none"``, by the hexagon's spiral and when
        ``n_visits`` is 0).
    region : "hexagon" or "disk"
        ``"hexagon"``: :func:`hexagon_offsets` or :func:`spiral_offsets` inside the
        inscribed circle (edge-rejection statistics); ``"disk"``: :func:`disk_offsets`
        (the field simulation).
    """
    if pattern not in ("random", "spiral", "none"):
        raise CellCoaddValueError(
            f"unknown dither pattern {pattern!r}; use 'random', 'spiral' or 'none'",
            value=pattern,
            allowed=("random", "spiral", "none"),
        )
    if region not in ("hexagon", "disk"):
        raise CellCoaddValueError(
            f"unknown dither region {region!r}; use 'hexagon' or 'disk'",
            value=region,
            allowed=("hexagon", "disk"),
        )
    if pattern == "none" or n_visits == 0:
        return np.zeros((n_visits, 2))
    if region == "disk":
        return disk_offsets(pattern, n_visits, radius, rng)
    if pattern == "random":
        return hexagon_offsets(n_visits, radius, rng)
    return spiral_offsets(n_visits, radius * np.sqrt(3.0) / 2.0)


def visit_rotations(n_visits: int, mode: RotationMode, rng: np.random.Generator) -> np.ndarray:
    """Rotation of the focal plane on the sky for each visit, radians.

    ``"random"`` draws uniform angles in [0, 2 pi) (camera rotator and parallactic angle vary
    between visits); ``"none"`` keeps every visit aligned with the sky axes.
    """
    if mode == "random":
        return rng.uniform(0.0, 2.0 * np.pi, n_visits)
    if mode == "none":
        return np.zeros(n_visits)
    raise CellCoaddValueError(
        f"unknown rotation mode {mode!r}; use 'random' or 'none'",
        value=mode,
        allowed=("random", "none"),
    )
