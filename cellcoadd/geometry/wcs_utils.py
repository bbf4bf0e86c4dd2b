"""Small WCS helpers shared by geometry, building and simulation.

Local sky coordinates ``(u, v)`` follow GalSim: arcsec on the tangent plane at a point,
``u`` towards decreasing RA (West) and ``v`` towards North, so a standard image with
East to the left has ``du/dx > 0``.
"""

from __future__ import annotations

import numpy as np
from astropy.wcs import WCS


def local_jacobian(wcs: WCS, x: float, y: float, step: float = 0.5) -> np.ndarray:
    """Jacobian ``[[du/dx, du/dy], [dv/dx, dv/dy]]`` (arcsec/pixel) of ``wcs`` at ``(x, y)``.

    ``x, y`` are 0-based pixel coordinates (pixel centres at integers). Central finite
    differences of ``step`` pixels; exact for a linear map and accurate to ~1e-9 relative
    for TAN projections over the scales used here.
    """
    xs = x + np.array([0.0, step, -step, 0.0, 0.0])
    ys = y + np.array([0.0, 0.0, 0.0, step, -step])
    ra, dec = wcs.all_pix2world(xs, ys, 0)
    u, v = gnomonic_uv(ra, dec, ra[0], dec[0])
    return np.array(
        [
            [(u[1] - u[2]) / (2 * step), (u[3] - u[4]) / (2 * step)],
            [(v[1] - v[2]) / (2 * step), (v[3] - v[4]) / (2 * step)],
        ]
    )


def gnomonic_uv(
    ra: np.ndarray, dec: np.ndarray, ra0: float, dec0: float
) -> tuple[np.ndarray, np.ndarray]:
    """Gnomonic projection (arcsec) of ``(ra, dec)`` (deg) about ``(ra0, dec0)`` (deg).

    ``u`` points West (decreasing RA), ``v`` North; see the module docstring.
    """
    ra_r, dec_r = np.radians(ra), np.radians(dec)
    ra0_r, dec0_r = np.radians(ra0), np.radians(dec0)
    dra = ra_r - ra0_r
    cos_c = np.sin(dec0_r) * np.sin(dec_r) + np.cos(dec0_r) * np.cos(dec_r) * np.cos(dra)
    east = np.cos(dec_r) * np.sin(dra) / cos_c
    north = (np.cos(dec0_r) * np.sin(dec_r) - np.sin(dec0_r) * np.cos(dec_r) * np.cos(dra)) / cos_c
    to_arcsec = 180.0 / np.pi * 3600.0
    return -east * to_arcsec, north * to_arcsec


def pixel_area(wcs: WCS, x: float, y: float) -> float:
    """Area of one pixel at ``(x, y)`` in arcsec^2 (absolute Jacobian determinant)."""
    return float(abs(np.linalg.det(local_jacobian(wcs, x, y))))
