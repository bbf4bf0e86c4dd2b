"""Test exposures with controlled WCS (scale, rotation, offset, SIP) and drawn sources."""

from __future__ import annotations

import galsim
import numpy as np
from astropy.wcs import WCS

from cellcoadd import Box, Exposure
from cellcoadd.geometry.wcs_utils import local_jacobian


def make_wcs(
    center: tuple[float, float],
    shape: tuple[int, int],
    pixel_scale: float,
    rotation_deg: float = 0.0,
    offset: tuple[float, float] = (0.0, 0.0),
    shear: float = 0.0,
    sip: bool = False,
) -> WCS:
    """TAN WCS whose pixel ((nx-1)/2 + dx, (ny-1)/2 + dy) is ``center`` (deg)."""
    ny, nx = shape
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"] if sip else ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = list(center)
    wcs.wcs.crpix = [(nx - 1) / 2 + offset[0] + 1, (ny - 1) / 2 + offset[1] + 1]
    theta = np.radians(rotation_deg)
    scale = pixel_scale / 3600.0
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    distort = np.array([[1 + shear, 0.0], [0.0, 1 - shear]])
    wcs.wcs.cd = np.array([[-scale, 0.0], [0.0, scale]]) @ rot @ distort
    if sip:
        from astropy.wcs import Sip

        a = np.zeros((4, 4))
        b = np.zeros((4, 4))
        a[2, 0], a[0, 2], a[1, 1] = 2e-6, -1e-6, 1.5e-6
        b[0, 2], b[2, 0], b[1, 1] = 1.5e-6, 1e-6, -1e-6
        a[3, 0], b[0, 3] = 1e-9, -1e-9
        wcs.sip = Sip(a, b, None, None, wcs.wcs.crpix)
    wcs.wcs.set()
    return wcs


def draw_sources(
    wcs: WCS,
    shape: tuple[int, int],
    sources: list[tuple[float, float, galsim.GSObject]],
    psf: galsim.GSObject,
    stamp: int = 81,
) -> np.ndarray:
    """Draw each ``(ra, dec, profile)`` convolved with ``psf`` through the local WCS."""
    image = galsim.ImageD(galsim.BoundsI(0, shape[1] - 1, 0, shape[0] - 1))
    for ra, dec, profile in sources:
        (x,), (y,) = wcs.all_world2pix([ra], [dec], 0)
        jac = local_jacobian(wcs, x, y)
        local = galsim.JacobianWCS(jac[0, 0], jac[0, 1], jac[1, 0], jac[1, 1])
        ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        half = stamp // 2
        bounds = galsim.BoundsI(ix - half, ix + half, iy - half, iy + half) & image.bounds
        sub = galsim.ImageD(bounds, wcs=local)
        galsim.Convolve(profile, psf).drawImage(
            image=sub, center=galsim.PositionD(x, y), method="auto"
        )
        image[bounds] += sub
    return image.array


def make_exposure(
    center: tuple[float, float],
    *,
    shape: tuple[int, int] = (160, 160),
    pixel_scale: float = 0.26,
    rotation_deg: float = 0.0,
    offset: tuple[float, float] = (0.0, 0.0),
    shear: float = 0.0,
    sip: bool = False,
    psf: galsim.GSObject | None = None,
    sources: list[tuple[float, float, galsim.GSObject]] = (),
    sky: float = 0.0,
    noise_sigma: float = 0.0,
    variance: float = 1.0,
    visit: int = 0,
    detector: int = 0,
    zero_point: float = 30.0,
    valid_box: Box | None = None,
    seed: int = 0,
    band: str = "r",
) -> Exposure:
    psf = psf or galsim.Moffat(beta=3.5, fwhm=0.9)
    wcs = make_wcs(center, shape, pixel_scale, rotation_deg, offset, shear, sip)
    image = draw_sources(wcs, shape, list(sources), psf) + sky
    if noise_sigma:
        image = image + np.random.default_rng(seed).normal(0.0, noise_sigma, shape)
    return Exposure(
        image=image,
        wcs=wcs,
        variance=variance if not noise_sigma else noise_sigma**2,
        psf=psf,
        visit=visit,
        detector=detector,
        band=band,
        zero_point=zero_point,
        valid_box=valid_box,
    )
