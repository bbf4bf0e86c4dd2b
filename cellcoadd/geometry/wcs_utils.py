"""Small WCS helpers shared by geometry, building and simulation.

Local sky coordinates ``(u, v)`` follow GalSim: arcsec on the tangent plane at a point,
``u`` towards decreasing RA (West) and ``v`` towards North, so a standard image with
East to the left has ``du/dx > 0``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from astropy.wcs import WCS

from cellcoadd.errors import CellCoaddValueError
from cellcoadd.geometry.exact_wcs import ExactWCS, exact_state, from_exact_state

if TYPE_CHECKING:
    import galsim

ARCSEC_PER_RADIAN = 180.0 / np.pi * 3600.0

#: GalSim's sky frame has u pointing West; FITS intermediate coordinates point East.
_U_TO_FITS = np.diag([-1.0, 1.0])


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


def jacobian_wcs(jacobian: np.ndarray) -> galsim.JacobianWCS:
    """GalSim WCS of the local Jacobian ``[[du/dx, du/dy], [dv/dx, dv/dy]]`` (arcsec/px).

    GalSim is imported here, so that importing this module stays cheap.
    """
    import galsim

    return galsim.JacobianWCS(
        float(jacobian[0, 0]), float(jacobian[0, 1]), float(jacobian[1, 0]), float(jacobian[1, 1])
    )


def tan_wcs(ra: float, dec: float, x: float, y: float, jacobian: np.ndarray) -> WCS:
    """TAN WCS putting ``(ra, dec)`` (deg) at 0-based pixel ``(x, y)`` with ``jacobian``.

    ``jacobian`` is ``[[du/dx, du/dy], [dv/dx, dv/dy]]`` in arcsec/pixel (GalSim sky
    frame); :func:`local_jacobian` of the result at ``(x, y)`` gives it back.
    """
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = [ra % 360.0, dec]
    wcs.wcs.crpix = [x + 1.0, y + 1.0]  # FITS pixels are 1-based
    wcs.wcs.cd = _U_TO_FITS @ np.asarray(jacobian, dtype=float) / 3600.0
    wcs.wcs.cunit = ["deg", "deg"]
    wcs.wcs.radesys = "ICRS"
    wcs.wcs.set()
    return wcs


def _tangent_basis(ra0: float, dec0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors of the tangent point and of East and North there."""
    a, d = np.radians(ra0), np.radians(dec0)
    center = np.array([np.cos(d) * np.cos(a), np.cos(d) * np.sin(a), np.sin(d)])
    east = np.array([-np.sin(a), np.cos(a), 0.0])
    north = np.array([-np.sin(d) * np.cos(a), -np.sin(d) * np.sin(a), np.cos(d)])
    if dec0 == 90.0:
        # A TAN WCS whose tangent point is the north pole defaults to LONPOLE = 0 (FITS
        # paper II), not 180 as everywhere else: its plane is turned by 180 deg from the
        # limit taken from below. Follow it, so that this agrees with the WCS there.
        return center, -east, -north
    return center, east, north


def gnomonic_uv(
    ra: np.ndarray, dec: np.ndarray, ra0: float, dec0: float
) -> tuple[np.ndarray, np.ndarray]:
    """Gnomonic projection (arcsec) of ``(ra, dec)`` (deg) about ``(ra0, dec0)`` (deg).

    ``u`` points West (decreasing RA), ``v`` North; see the module docstring. Positions
    90 deg or more from the tangent point have no projection: NaN.
    """
    center, east, north = _tangent_basis(ra0, dec0)
    ra_r, dec_r = np.radians(ra), np.radians(dec)
    cos_dec = np.cos(dec_r)
    q = np.stack([cos_dec * np.cos(ra_r), cos_dec * np.sin(ra_r), np.sin(dec_r)], axis=-1)
    cos_c = q @ center
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(cos_c > 1e-9, ARCSEC_PER_RADIAN / cos_c, np.nan)
    return -(q @ east) * scale, (q @ north) * scale


def gnomonic_radec(
    u: np.ndarray, v: np.ndarray, ra0: float, dec0: float
) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`gnomonic_uv`: ``(ra, dec)`` in deg (RA in [0, 360)) of ``(u, v)``."""
    center, east, north = _tangent_basis(ra0, dec0)
    xi = -np.asarray(u, dtype=float)[..., None] / ARCSEC_PER_RADIAN
    eta = np.asarray(v, dtype=float)[..., None] / ARCSEC_PER_RADIAN
    p = center + xi * east + eta * north
    ra = np.degrees(np.arctan2(p[..., 1], p[..., 0])) % 360.0
    dec = np.degrees(np.arctan2(p[..., 2], np.hypot(p[..., 0], p[..., 1])))
    return ra, dec


def pixel_area(wcs: WCS, x: float, y: float) -> float:
    """Area of one pixel at ``(x, y)`` in arcsec^2 (absolute Jacobian determinant)."""
    return float(abs(np.linalg.det(local_jacobian(wcs, x, y))))


def shifted_wcs(wcs: WCS, x_start: int, y_start: int, *, canonical: bool = True) -> WCS:
    """Copy of ``wcs`` whose array pixel (0, 0) is its pixel ``(x_start, y_start)``: the
    WCS of a cutout starting there.

    Exact for TAN, TPV and SIP: their distortions are functions of the offset from the
    reference pixel, which moves with it (the SIP polynomials carry their own copy of
    it). Lookup-table distortions (``cpdis``, ``det2im``) are refused. The copy is put in
    :func:`canonical_wcs` form unless ``canonical=False``; the shift of a canonical WCS
    (an :class:`~cellcoadd.geometry.exact_wcs.ExactWCS`) is canonical already, since its
    pickle keeps the new reference pixel exactly (no round trip is made, ~0.1 ms).
    """
    from astropy.wcs import Sip

    if wcs.cpdis1 is not None or wcs.cpdis2 is not None or wcs.det2im1 is not None:
        raise CellCoaddValueError("cannot shift a WCS with lookup-table distortions")
    out = wcs.deepcopy()
    out.wcs.crpix = out.wcs.crpix - np.array([x_start, y_start], dtype=float)
    if out.sip is not None:
        sip = out.sip
        out.sip = Sip(sip.a, sip.b, sip.ap, sip.bp, out.wcs.crpix)
    out.wcs.set()
    return canonical_wcs(out) if canonical and not isinstance(out, ExactWCS) else out


def canonical_wcs(wcs: WCS) -> ExactWCS:
    """``wcs`` as an :class:`~cellcoadd.geometry.exact_wcs.ExactWCS`, in the form it takes
    after being sent to another process.

    The copy has the same numerical parameters, bit for bit (wcslib's form: a CD matrix
    becomes PC with CDELT = 1, the same product), and pickles exactly, so results are
    bit-identical whether a computation runs here or in a worker process. (A plain
    astropy WCS pickles through 14-digit FITS cards, which changes its last bits.)
    """
    return from_exact_state(exact_state(wcs))
