"""Rubin's ring sky map (LSST ``RingsSkyMap``, version 1): ring layout, tract ids, ownership.

The sphere is cut into ``n_rings`` declination rings of equal width plus two polar caps
that together count as one more ring. Each ring is split in RA into equal tracts, as many
as fit along the ring's edge nearest the equator, plus one. Tract ids count from the
south cap (0) ring by ring northwards, eastwards within a ring from ``ra_start``; the north
cap has the last id. A position belongs to the tract whose ring holds its declination and
whose centre RA is nearest (RA ranges centred on the tract centres, half-open).

Every tract is a square TAN projection centred on the tract centre, just large enough to
hold the points ``half ring width + tract_overlap`` from the centre towards the four
cardinal directions, then grown to a whole number of patches, keeping the centre. The
derivation from Rubin's published description is in ``docs/geometry.md``; this module
computes the same numbers in closed form.

Angles are computed in radians in the same order as the published algorithm, so that
integer decisions (ring counts, ring and tract of a position) agree bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from cellcoadd.errors import CellCoaddIndexError, ConfigError
from cellcoadd.geometry.regions import InnerRegion

__all__ = ["LsstRings", "LsstRingRegion", "lsst_tract_box"]


@dataclass(frozen=True)
class LsstRings:
    """The ring layout of Rubin's ring sky map.

    Parameters
    ----------
    n_rings : int
        Declination rings, not counting the two polar caps (Rubin's ``numRings``).
    ra_start : float
        RA of the first tract centre of every ring, deg (Rubin's ``raStart``).
    """

    n_rings: int
    ra_start: float = 0.0

    @property
    def ring_size(self) -> float:
        """Width of a ring in declination, radians (the two caps make one more ring)."""
        return math.pi / (self.n_rings + 1)

    @cached_property
    def ring_counts(self) -> tuple[int, ...]:
        """Tracts in each ring, south to north."""
        size = self.ring_size
        counts = []
        for ring in range(self.n_rings):
            start = size * (ring + 0.5) - 0.5 * math.pi
            stop = start + size
            nearest_equator = min(math.fabs(start), math.fabs(stop))
            # as many tracts as fit along the ring's longest edge, plus one
            counts.append(int(2 * math.pi * math.cos(nearest_equator) / size) + 1)
        return tuple(counts)

    @cached_property
    def first_ids(self) -> np.ndarray:
        """Id of the first tract (at ``ra_start``) of each ring; the south cap is tract 0."""
        return np.concatenate([[1], 1 + np.cumsum(self.ring_counts)]).astype(np.int64)[:-1]

    @property
    def n_tracts(self) -> int:
        return sum(self.ring_counts) + 2

    def ring_and_index(self, tract_id: int) -> tuple[int, int]:
        """``(ring, index in ring)``; ring -1 is the south cap, ``n_rings`` the north cap."""
        if not 0 <= tract_id < self.n_tracts:
            raise CellCoaddIndexError(
                f"tract {tract_id} is not in this sky map ({self.n_tracts} tracts)",
                value=tract_id,
                allowed=(0, self.n_tracts),
            )
        if tract_id == 0:
            return -1, 0
        if tract_id == self.n_tracts - 1:
            return self.n_rings, 0
        ring = int(np.searchsorted(self.first_ids, tract_id, side="right")) - 1
        return ring, tract_id - int(self.first_ids[ring])

    def center(self, tract_id: int) -> tuple[float, float]:
        """Tract centre (tangent point) ``(ra, dec)`` in deg; the caps are centred at RA 0."""
        ring, index = self.ring_and_index(tract_id)
        if ring == -1:
            return 0.0, -90.0
        if ring == self.n_rings:
            return 0.0, 90.0
        dec = self.ring_size * (ring + 1) - 0.5 * math.pi
        ra = (2 * math.pi * index / self.ring_counts[ring] + math.radians(self.ra_start)) % (
            2 * math.pi
        )
        return math.degrees(ra), math.degrees(dec)

    def dec_range(self, tract_id: int) -> tuple[float, float]:
        """Declination range (deg) of the tract's ring or cap."""
        ring, _ = self.ring_and_index(tract_id)
        first = self.ring_size * 0.5 - 0.5 * math.pi
        low = -0.5 * math.pi if ring == -1 else first + ring * self.ring_size
        high = 0.5 * math.pi if ring == self.n_rings else first + (ring + 1) * self.ring_size
        return math.degrees(low), math.degrees(high)

    def find_tract(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        """Id of the tract owning each position (deg); vectorised.

        A declination below the first ring's start is the south cap, above the last
        ring's end the north cap (a position exactly on either edge belongs to the ring).
        Within a ring the tract is the one whose centre RA is nearest, rounding half up.
        """
        ra_r = np.deg2rad(np.atleast_1d(np.asarray(ra, dtype=float)))
        dec_r = np.deg2rad(np.atleast_1d(np.asarray(dec, dtype=float)))
        first = self.ring_size * 0.5 - 0.5 * np.pi
        ring = np.zeros(dec_r.shape, dtype=np.int64)
        middle = (dec_r >= first) & (dec_r <= -first)
        ring[middle] = ((dec_r[middle] - first) / self.ring_size).astype(np.int64)
        ring[dec_r < first] = -1
        ring[(dec_r > -first) | (ring >= self.n_rings)] = self.n_rings
        out = np.where(ring < 0, 0, self.n_tracts - 1).astype(np.int64)
        in_ring = np.nonzero((ring >= 0) & (ring < self.n_rings))[0]
        counts = np.asarray(self.ring_counts, dtype=np.int64)[ring[in_ring]]
        delta = (ra_r[in_ring] - np.deg2rad(self.ra_start)) % (2.0 * np.pi)
        index = (delta / (2.0 * np.pi / counts) + 0.5).astype(np.int64)
        index[index == counts] = 0  # the last half slice wraps to the tract at ra_start
        out[in_ring] = self.first_ids[ring[in_ring]] + index
        return out


def lsst_tract_box(
    n_rings: int, tract_overlap: float, pixel_scale: float, patch_inner: int
) -> tuple[int, int]:
    """Patches along a tract side, and the 0-based tract pixel of the tangent point.

    Parameters
    ----------
    n_rings : int
        Rings of the sky map.
    tract_overlap : float
        Rubin's ``tractOverlap``, deg.
    pixel_scale : float
        arcsec/pixel.
    patch_inner : int
        Side of a patch inner region, pixels.

    Returns
    -------
    patches_per_tract, tangent_pixel : int
        The tract is ``patches_per_tract * patch_inner`` pixels square and its tangent
        point is at pixel ``(tangent_pixel, tangent_pixel)`` (an integer: pixel centres).

    Notes
    -----
    The four points at ``half ring width + tract_overlap`` from the centre along the
    cardinal directions lie on the projection axes at ``+-a = tan(d) / scale`` pixels from
    the tangent point. Their float box ``[-a, a]`` becomes the integer pixel box
    ``[ceil(-a - 1/2), floor(a + 1/2)]`` (every pixel it touches); each side is then grown to
    a whole number of patches, the lower edge moving down by half the growth (rounded
    down), and the box is shifted to start at pixel 0.
    """
    half_side = 0.5 * math.pi / (n_rings + 1) + math.radians(tract_overlap)
    if not half_side < 0.5 * math.pi:
        raise ConfigError(
            f"tract_overlap={tract_overlap} deg plus half a ring reaches 90 deg: no TAN tract"
        )
    a = math.tan(half_side) / math.radians(pixel_scale / 3600.0)
    low = math.ceil(-a - 0.5)
    size = math.floor(a + 0.5) - low + 1
    patches = (size + patch_inner - 1) // patch_inner
    low -= (patches * patch_inner - size) // 2
    return patches, -low


@dataclass(frozen=True)
class LsstRingRegion(InnerRegion):
    """The positions Rubin's ring sky map gives to tract ``tract_id``."""

    rings: LsstRings
    tract_id: int

    def contains(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        return self.rings.find_tract(ra, dec) == self.tract_id
