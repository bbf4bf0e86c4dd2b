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


def ra_slice_index(ra: np.ndarray, n_ra: int | np.ndarray) -> np.ndarray:
    """Index of the half-open RA range ``[j, j + 1) * 360 / n_ra`` holding ``ra`` (deg)."""
    ra = np.mod(np.asarray(ra, dtype=float), 360.0)
    return np.minimum(np.floor(ra * (n_ra / 360.0)).astype(np.int64), n_ra - 1)


@dataclass(frozen=True)
class RingRegion(InnerRegion):
    """``dec_min <= dec < dec_max`` and RA in slice ``ra_index`` of ``n_ra`` equal slices.

    The north polar cap has ``dec_max > 90`` so that dec = 90 is included. RA slices are
    found with :func:`ra_slice_index`, the same computation the sky map's lookup uses, so
    ownership is decided identically everywhere (no rounding disagreement at RA = 0/360).
    """

    dec_min: float
    dec_max: float
    n_ra: int = 1
    ra_index: int = 0

    @property
    def ra_width(self) -> float:
        return 360.0 / self.n_ra

    @property
    def ra_min(self) -> float:
        return self.ra_index * self.ra_width

    def contains(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        dec = np.asarray(dec, dtype=float)
        in_dec = (dec >= self.dec_min) & (dec < self.dec_max)
        return in_dec & (ra_slice_index(ra, self.n_ra) == self.ra_index)


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
