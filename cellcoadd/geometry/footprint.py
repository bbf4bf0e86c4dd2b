"""Footprints of inputs on the sky and on a tract: corners, HEALPix pixels, areas, which
boxes a footprint covers, and which tracts it may touch.

A footprint is the quadrilateral of an input's valid box corners, pushed outward by a
margin (WCS distortion bends the edges between the corners), as RA/Dec (deg) on the sky
or as pixel positions on a tract. HEALPix pixels (nested, :mod:`hpgeom`) are the spatial
key of the exposure index: no RA wrap, no singular pole.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import hpgeom
import numpy as np

from cellcoadd.errors import ConfigError
from cellcoadd.geometry.box import Box

#: Pixels by which a footprint's corners are pushed outward (distortion between corners).
FOOTPRINT_MARGIN = 8.0


def box_corners(box: Box, margin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``x, y`` of the corners of ``box`` (pixel edges, in order around it), pushed
    outward by ``margin`` pixels."""
    x0, x1 = box.x_start - 0.5 - margin, box.x_stop - 0.5 + margin
    y0, y1 = box.y_start - 0.5 - margin, box.y_stop - 0.5 + margin
    return np.array([x0, x1, x1, x0]), np.array([y0, y0, y1, y1])


def sky_corners(wcs: object, box: Box, margin: float = FOOTPRINT_MARGIN) -> np.ndarray:
    """RA/Dec (deg, RA in [0, 360)) of the corners of ``box`` pushed outward by
    ``margin`` pixels through ``wcs`` (an astropy WCS, 0-based): shape ``(4, 2)``."""
    x, y = box_corners(box, margin)
    ra, dec = wcs.all_pix2world(x, y, 0)  # type: ignore[attr-defined]
    return np.column_stack([np.mod(ra, 360.0), dec])


def healpix_pixels(nside: int, corners: np.ndarray) -> np.ndarray:
    """Nested HEALPix pixels overlapping the convex polygon ``corners`` ((n, 2) RA/Dec, deg)."""
    return np.asarray(
        hpgeom.query_polygon(nside, corners[:, 0], corners[:, 1], inclusive=True, nest=True),
        dtype=np.int64,
    )


def polygon_area(corners: np.ndarray) -> float:
    """Area of a small convex polygon (RA/Dec deg corners), deg^2, on its tangent plane."""
    ra, dec = np.radians(corners[:, 0]), np.radians(corners[:, 1])
    xyz = np.column_stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)])
    centre = xyz.mean(axis=0)
    centre /= np.linalg.norm(centre)
    east = np.cross([0.0, 0.0, 1.0], centre)
    east = east / np.linalg.norm(east) if np.linalg.norm(east) > 1e-12 else np.array([0, 1.0, 0])
    north = np.cross(centre, east)
    scale = xyz @ centre  # gnomonic projection
    u, v = (xyz @ east) / scale, (xyz @ north) / scale
    area = 0.5 * abs(np.dot(u, np.roll(v, -1)) - np.dot(v, np.roll(u, -1)))
    return float(np.degrees(np.degrees(area)))


def quads_covering_boxes(quads: Sequence[np.ndarray], boxes: Sequence[Box]) -> np.ndarray:
    """How many of the convex quadrilaterals ``quads`` (each ``(4, 2)`` ``x, y``, either
    winding) hold the whole of each box (its four pixel-edge corners): shape
    ``(len(boxes),)``. Chunked: memory bounded whatever the number of quads."""
    count = np.zeros(len(boxes))
    if not quads or not boxes:
        return count
    corners = [box_corners(b) for b in boxes]
    points = np.stack([np.column_stack(c) for c in corners]).reshape(-1, 2)  # 4 per box
    for start in range(0, len(quads), 64):
        part = np.stack(quads[start : start + 64])  # (m, 4, 2)
        edges = np.roll(part, -1, axis=1) - part
        rel = points[None, None, :, :] - part[:, :, None, :]  # (m, 4, p, 2)
        cross = edges[:, :, None, 0] * rel[..., 1] - edges[:, :, None, 1] * rel[..., 0]
        # inside a convex quad: on the same side of its four edges (either winding)
        inside = np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)  # (m, p)
        count += inside.reshape(len(part), len(boxes), 4).all(axis=2).sum(axis=0)
    return count


def circle_pixels(nside: int, ra: float, dec: float, radius_deg: float) -> np.ndarray:
    """Nested HEALPix pixels touching the circle of ``radius_deg`` around ``ra, dec``."""
    return np.asarray(
        hpgeom.query_circle(nside, ra, dec, radius_deg, inclusive=True, nest=True),
        dtype=np.int64,
    )


def parent_pixels(pixels: Iterable[int], nside: int, coarse_nside: int) -> np.ndarray:
    """The nested pixels at ``coarse_nside`` holding each of ``pixels`` (nested, ``nside``)."""
    if coarse_nside > nside:
        raise ConfigError(f"coarse nside {coarse_nside} is finer than nside {nside}")
    shift = 2 * (int(np.log2(nside)) - int(np.log2(coarse_nside)))
    return np.unique(np.asarray(list(pixels), dtype=np.int64) >> shift)


def angular_distance(ra0: float, dec0: float, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
    """Great-circle distances (deg) from ``ra0, dec0`` to each ``ra, dec`` (deg)."""
    r0, d0, r, d = (np.radians(v) for v in (ra0, dec0, np.asarray(ra), np.asarray(dec)))
    cos = np.sin(d0) * np.sin(d) + np.cos(d0) * np.cos(d) * np.cos(r - r0)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def in_ra_dec_box(
    ra: np.ndarray, dec: np.ndarray, region: tuple[float, float, float, float]
) -> np.ndarray:
    """Whether each position (deg) is in ``region = (ra0, ra1, dec0, dec1)``: RA from
    ``ra0`` eastward to ``ra1`` (``ra0 > ra1`` wraps through 0: ``350, 10`` is 20 deg wide),
    ``dec0 <= dec <= dec1``."""
    ra0, ra1, dec0, dec1 = region
    width = np.mod(ra1 - ra0, 360.0) or (360.0 if ra1 != ra0 else 0.0)
    inside_ra = np.mod(np.asarray(ra) - ra0, 360.0) <= width
    return inside_ra & (np.asarray(dec) >= dec0) & (np.asarray(dec) <= dec1)


def check_region(region: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    """``region`` as floats, after checking it (see :func:`in_ra_dec_box`).

    Raises
    ------
    ConfigError
        When a value is not finite, RA is outside [0, 360], Dec outside [-90, 90] or
        ``dec0 > dec1``.
    """
    values = tuple(float(v) for v in region)
    if len(values) != 4 or not all(np.isfinite(values)):
        raise ConfigError(f"region {region!r}: give four finite numbers RA0,RA1,DEC0,DEC1")
    ra0, ra1, dec0, dec1 = values
    if not (0.0 <= ra0 <= 360.0 and 0.0 <= ra1 <= 360.0):
        raise ConfigError(f"region {region!r}: RA0 and RA1 must be in [0, 360] deg")
    if not (-90.0 <= dec0 <= dec1 <= 90.0):
        raise ConfigError(f"region {region!r}: need -90 <= DEC0 <= DEC1 <= 90 deg")
    return ra0, ra1, dec0, dec1
