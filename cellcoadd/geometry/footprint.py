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

from cellcoadd.errors import CellCoaddRangeError, ConfigError, GeometryError
from cellcoadd.geometry.box import Box

#: Pixels by which a footprint's corners are pushed outward (distortion between corners).
FOOTPRINT_MARGIN = 8.0

#: Finest HEALPix resolution of a spatial key: nside 65536 pixels are 3.2 arcsec on a side,
#: so an LSST detector (13 arcmin) overlaps ~60,000 of them. A finer key stores more rows
#: than any query can use (nside 67108864 made a 337 MB index of one exposure in 120 s).
MAX_NSIDE = 1 << 16

#: Most HEALPix pixels one footprint may overlap (an LSST detector at :data:`MAX_NSIDE`
#: overlaps ~95,000, counted as :func:`estimated_pixels` does; at nside 512, ~10). More
#: means a WCS of the wrong scale or an nside too fine, and costs minutes and gigabytes.
MAX_FOOTPRINT_PIXELS = 1 << 18


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


def check_nside(nside: int) -> int:
    """``nside`` after checking it is a power of 2 in ``1 ..`` :data:`MAX_NSIDE`.

    Raises
    ------
    CellCoaddRangeError
        Naming the value and the allowed range.
    """
    if isinstance(nside, bool) or not isinstance(nside, (int, np.integer)):
        raise CellCoaddRangeError(
            f"HEALPix nside {nside!r} is not an integer (a power of 2, 1 to {MAX_NSIDE})",
            value=nside,
            low=1,
            high=MAX_NSIDE,
        )
    nside = int(nside)
    if not 1 <= nside <= MAX_NSIDE or nside & (nside - 1):
        raise CellCoaddRangeError(
            f"HEALPix nside {nside} is not a power of 2 from 1 to {MAX_NSIDE}",
            value=nside,
            low=1,
            high=MAX_NSIDE,
        )
    return nside


def estimated_pixels(nside: int, corners: np.ndarray) -> float:
    """About how many HEALPix pixels (``nside``) the polygon ``corners`` ((n, 2) RA/Dec,
    deg) overlaps, from its circumscribed cap grown by two pixels (no pixel is listed):
    an upper bound within a factor ~2 for a quadrilateral footprint."""
    ra, dec = np.radians(corners[:, 0]), np.radians(corners[:, 1])
    xyz = np.column_stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)])
    centre = xyz.mean(axis=0)
    norm = np.linalg.norm(centre)
    if not norm > 1e-12:  # corners around a great circle: a hemisphere or more
        return 12.0 * nside * nside
    radius = float(np.max(np.arccos(np.clip(xyz @ (centre / norm), -1.0, 1.0))))
    pixel_area = 4.0 * np.pi / (12.0 * nside * nside)  # sr
    radius = min(radius + 2.0 * np.sqrt(pixel_area), np.pi)
    return float(min(2.0 * np.pi * (1.0 - np.cos(radius)) / pixel_area, 12.0 * nside * nside))


def healpix_pixels(
    nside: int, corners: np.ndarray, max_pixels: int | None = MAX_FOOTPRINT_PIXELS
) -> np.ndarray:
    """Nested HEALPix pixels overlapping the convex polygon ``corners`` ((n, 2) RA/Dec, deg).

    Parameters
    ----------
    nside : int
        HEALPix resolution (:func:`check_nside`).
    corners : numpy.ndarray
        ``(n, 2)`` RA/Dec (deg) in order around the polygon, ``n >= 3``.
    max_pixels : int or None
        Refuse, before listing any pixel, a polygon estimated
        (:func:`estimated_pixels`) to overlap more pixels; None: no bound.

    Raises
    ------
    GeometryError
        For corners that are not finite, a polygon over ``max_pixels`` pixels (naming
        the estimate and the bound), or a degenerate one (two corners in one place or on
        one line, as a pixel scale of 1e-7 arcsec gives).
    """
    corners = np.asarray(corners, dtype=float)
    if corners.ndim != 2 or corners.shape[0] < 3 or corners.shape[1] != 2:
        raise GeometryError(f"a footprint polygon needs (n >= 3, 2) corners, got {corners.shape}")
    if not np.all(np.isfinite(corners)):
        raise GeometryError(f"footprint corners {corners.tolist()} are not all finite")
    if max_pixels is not None:
        estimate = estimated_pixels(nside, corners)
        if estimate > max_pixels:
            raise GeometryError(
                f"the footprint would overlap ~{estimate:.3g} HEALPix pixels at nside {nside}, "
                f"more than the {max_pixels} accepted (a WCS of the wrong pixel scale, or an "
                "nside too fine?)",
                value=estimate,
                allowed=max_pixels,
            )
    try:
        found = hpgeom.query_polygon(nside, corners[:, 0], corners[:, 1], inclusive=True, nest=True)
    except (ValueError, RuntimeError) as err:  # hpgeom: "Polygon has degenerate corner."
        shown = ", ".join(f"({ra:.9f}, {dec:.9f})" for ra, dec in corners)
        raise GeometryError(
            f"a degenerate footprint polygon ({err}): its corners {shown} (deg) are not "
            "distinct points around a convex area (a pixel scale far too small?)",
            value=corners.tolist(),
        ) from None
    return np.asarray(found, dtype=np.int64)


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
