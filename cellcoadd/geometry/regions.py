"""Tract inner regions: the part of the sky each tract owns.

Every sky position is owned by exactly one tract. Ring tessellations own half-open
declination bands split into half-open RA ranges (plus two polar caps); explicit tract
centres own the positions nearer to them than to any other centre (ties go to the lowest
tract id), limited to the tract's pixel box by :meth:`Tract.contains_inner`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def unit_vectors(ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
    """Unit vectors ``(n, 3)`` of positions in deg."""
    ra_r, dec_r = np.radians(ra), np.radians(dec)
    cos_dec = np.cos(dec_r)
    return np.stack([cos_dec * np.cos(ra_r), cos_dec * np.sin(ra_r), np.sin(dec_r)], axis=-1)


class InnerRegion:
    """Interface: ``contains(ra, dec) -> bool array`` (deg)."""

    def contains(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError


@dataclass(frozen=True)
class RingRegion(InnerRegion):
    """``dec_min <= dec < dec_max`` and ``ra_min <= ra < ra_min + ra_width`` (deg, RA mod 360).

    The north polar cap has ``dec_max > 90`` so that dec = 90 is included.
    """

    dec_min: float
    dec_max: float
    ra_min: float = 0.0
    ra_width: float = 360.0

    def contains(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        ra = np.mod(np.asarray(ra, dtype=float), 360.0)
        dec = np.asarray(dec, dtype=float)
        in_dec = (dec >= self.dec_min) & (dec < self.dec_max)
        if self.ra_width >= 360.0:
            return in_dec
        offset = np.mod(ra - self.ra_min, 360.0)
        return in_dec & (offset < self.ra_width)


@dataclass(frozen=True)
class NearestCenterRegion(InnerRegion):
    """Positions whose nearest tract centre is centre ``index`` (ties to the lowest index)."""

    centers: tuple[tuple[float, float], ...]
    index: int

    def contains(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        return nearest_center(self.centers, ra, dec) == self.index


def nearest_center(
    centers: tuple[tuple[float, float], ...], ra: np.ndarray, dec: np.ndarray
) -> np.ndarray:
    """Index of the nearest centre (deg) for each position; argmax keeps the lowest on ties."""
    center_ra, center_dec = np.array(centers, dtype=float).T
    ref = unit_vectors(center_ra, center_dec)
    pos = unit_vectors(np.atleast_1d(ra).astype(float), np.atleast_1d(dec).astype(float))
    out = np.empty(pos.shape[0], dtype=np.int64)
    chunk = max(1, 4_000_000 // max(1, len(centers)))  # bound the (n, m) temporary
    for start in range(0, pos.shape[0], chunk):
        out[start : start + chunk] = np.argmax(pos[start : start + chunk] @ ref.T, axis=1)
    return out
