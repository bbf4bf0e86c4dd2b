"""Dither patterns: per-visit pointing offsets and rotations (paper section 5.2, Fig. 5).

Offsets are flat-sky ``(x, y)`` displacements of the optical axis from the nominal field
centre, arcsec. As in the paper they are confined to a hexagon whose circumradius is about
the focal-plane radius: ``"random"`` draws them uniformly inside it, ``"spiral"`` walks an
Archimedean spiral inside its inscribed circle.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

DitherPattern = Literal["random", "spiral"]
RotationMode = Literal["random", "none"]


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
        raise ValueError("n_points and n_coils must be positive")
    step = np.arange(1, n_points + 1) / n_points
    angle = 2.0 * np.pi * n_coils * step
    radius = max_radius * step
    pattern = np.column_stack([radius * np.cos(angle), radius * np.sin(angle)])
    return pattern[np.arange(n_visits) % n_points]


def dither_offsets(
    pattern: DitherPattern,
    n_visits: int,
    circumradius: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Per-visit pointing offsets, arcsec, shape ``(n_visits, 2)``.

    Parameters
    ----------
    pattern : "random" or "spiral"
        Uniform in the hexagon, or the spiral inscribed in it.
    n_visits : int
        Number of visits.
    circumradius : float
        Hexagon circumradius, arcsec.
    rng : numpy.random.Generator
        Random stream (unused by the spiral).
    """
    if pattern == "random":
        return hexagon_offsets(n_visits, circumradius, rng)
    if pattern == "spiral":
        return spiral_offsets(n_visits, circumradius * np.sqrt(3.0) / 2.0)
    raise ValueError(f"unknown dither pattern {pattern!r}; use 'random' or 'spiral'")


def visit_rotations(n_visits: int, mode: RotationMode, rng: np.random.Generator) -> np.ndarray:
    """Rotation of the focal plane on the sky for each visit, radians.

    ``"random"`` draws uniform angles in [0, 2 pi) (camera rotator and parallactic angle vary
    between visits); ``"none"`` keeps every visit aligned with the sky axes.
    """
    if mode == "random":
        return rng.uniform(0.0, 2.0 * np.pi, n_visits)
    if mode == "none":
        return np.zeros(n_visits)
    raise ValueError(f"unknown rotation mode {mode!r}; use 'random' or 'none'")
