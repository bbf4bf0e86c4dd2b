"""Survey-format PSF model files (PSFEx ``.psf`` and Piff) made for tests.

Both factories write a PSF whose size varies across a CCD by a known, measurable amount, so
tests of the library's PSF wrappers can check position dependence, not only the centre.

Conventions (see ``docs/inputs.md``; ``tests/test_survey_psf.py`` checks them):

* PSFEx polynomials are in **1-based** FITS image coordinates (``X_IMAGE``/``Y_IMAGE``), and the
  stamps are the *pixel-included* (effective) PSF sampled every ``PSF_SAMP`` image pixels, with
  the profile centre on the central sample of an odd-sized stamp.
* The Piff model is fitted in the coordinates of the galsim images its stars were cut from; this
  factory uses FITS-like **1-based** bounds, as ``piff`` does when it reads FITS images.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import fitsio
import galsim
import numpy as np

__all__ = [
    "PiffFileInfo",
    "PsfexFileInfo",
    "build_piff_model",
    "measure_fwhm",
    "moffat_effective_stamp",
    "write_psfex_file",
]

MOFFAT_BETA = 3.5
"""Moffat index of the PSF profiles written by this module (dimensionless)."""


@dataclasses.dataclass(frozen=True)
class PsfexFileInfo:
    """What a test needs to know about a file written by :func:`write_psfex_file`.

    Attributes
    ----------
    path : pathlib.Path
        The ``.psf`` file.
    size : int
        Stamp side ``PSFAXIS1 == PSFAXIS2`` (PSFEx samples).
    samp : float
        ``PSF_SAMP``: image pixels per PSFEx sample.
    nx, ny : int
        CCD size (pixels) the polynomial spans.
    pixel_scale : float
        Nominal pixel scale (arcsec / pixel) used to turn ``fwhm_range`` into pixels.
    fwhm_pix : tuple of float
        Moffat FWHM (image pixels, pixel response *not* included) at 1-based image position
        ``(1, 1)`` and at ``(nx, ny)``; it varies linearly in ``x + y`` between them.
    polzero, polscal : tuple of float
        ``(POLZERO1, POLZERO2)`` and ``(POLSCAL1, POLSCAL2)`` (1-based image pixels).
    poldeg : int
        ``POLDEG1``.
    """

    path: Path
    size: int
    samp: float
    nx: int
    ny: int
    pixel_scale: float
    fwhm_pix: tuple[float, float]
    polzero: tuple[float, float]
    polscal: tuple[float, float]
    poldeg: int


@dataclasses.dataclass(frozen=True)
class PiffFileInfo:
    """What a test needs to know about a file written by :func:`build_piff_model`.

    Attributes
    ----------
    path : pathlib.Path
        The Piff model file (FITS).
    nx, ny : int
        CCD size (pixels).
    pixel_scale : float
        Pixel scale (arcsec / pixel) of the default ``galsim.PixelScale`` WCS.
    fwhm_arcsec : tuple of float
        Input Moffat FWHM (arcsec, pixel *not* included) at 1-based ``(1, 1)`` and ``(nx, ny)``.
    origin : int
        Image-coordinate origin of the fit: 1 means pixel centres run ``1 .. nx``.
    nstars : int
        Number of noise-free stars the model was fitted on.
    chipnum : int
        Chip number of the model (``psf.draw(..., chipnum=chipnum)``).
    """

    path: Path
    nx: int
    ny: int
    pixel_scale: float
    fwhm_arcsec: tuple[float, float]
    origin: int
    nstars: int
    chipnum: int


def moffat_effective_stamp(fwhm_pix: float, size: int, samp: float) -> np.ndarray:
    """Pixel-convolved Moffat sampled like a PSFEx stamp.

    Parameters
    ----------
    fwhm_pix : float
        FWHM of the Moffat before the pixel response (image pixels).
    size : int
        Stamp side (samples); must be odd so the centre falls on the central sample.
    samp : float
        Sample spacing (image pixels per sample, PSFEx's ``PSF_SAMP``).

    Returns
    -------
    numpy.ndarray
        ``(size, size)`` float64 array of the effective PSF (Moffat convolved with a 1-pixel
        box) evaluated at the sample points, peak on element ``[size // 2, size // 2]``,
        normalised to sum to 1 (dimensionless).
    """
    if size % 2 != 1:
        raise ValueError(f"size must be odd, got {size}")
    effective = galsim.Convolve(galsim.Moffat(beta=MOFFAT_BETA, fwhm=fwhm_pix), galsim.Pixel(1.0))
    arr = effective.drawImage(nx=size, ny=size, scale=samp, method="no_pixel").array
    return arr / arr.sum()


def write_psfex_file(
    path: str | Path,
    *,
    size: int = 25,
    samp: float = 1.0,
    fwhm_range: tuple[float, float] = (0.9, 0.96),
    nx: int = 2048,
    ny: int = 4096,
    pixel_scale: float = 0.263,
    poldeg: int = 1,
) -> PsfexFileInfo:
    """Write a PSFEx ``.psf`` file whose PSF widens from one CCD corner to the other.

    The model is ``P(x, y) = B0 + xs * B1 + ys * B2`` with ``xs = (x - POLZERO1) / POLSCAL1``
    and ``ys = (y - POLZERO2) / POLSCAL2`` in 1-based image pixels, ``POLZERO`` the CCD centre
    and ``POLSCAL`` the CCD size, so ``xs, ys`` run over ``[-0.5, 0.5]``.  With ``E(f)`` the
    effective (pixel-included) Moffat stamp of FWHM ``f``, ``B0 = (E(f0) + E(f1)) / 2`` and
    ``B1 = B2 = (E(f1) - E(f0)) / 2``: the model is exactly ``E(f0)`` at ``(0.5, 0.5)``
    (the outer corner of pixel 1,1) and ``E(f1)`` at ``(nx + 0.5, ny + 0.5)``.

    Parameters
    ----------
    path : str or pathlib.Path
        Output file (overwritten).
    size : int, optional
        Stamp side in samples (odd).
    samp : float, optional
        ``PSF_SAMP`` (image pixels per sample).
    fwhm_range : tuple of float, optional
        Moffat FWHM (arcsec, before the pixel) at the low and the high corner.
    nx, ny : int, optional
        CCD size (pixels).
    pixel_scale : float, optional
        Pixel scale (arcsec / pixel) converting ``fwhm_range`` to pixels.
    poldeg : int, optional
        ``POLDEG1`` (1 or 2); second-order components are written as zeros.

    Returns
    -------
    PsfexFileInfo
        The file's parameters.
    """
    if poldeg not in (1, 2):
        raise ValueError(f"poldeg must be 1 or 2, got {poldeg}")
    path = Path(path)
    f0, f1 = (f / pixel_scale for f in fwhm_range)
    e0 = moffat_effective_stamp(f0, size, samp)
    e1 = moffat_effective_stamp(f1, size, samp)
    ncoeff = (poldeg + 1) * (poldeg + 2) // 2
    # Order of the components as PSFEx (and galsim.des.DES_PSFEx) use it:
    # 1, x, [x^2,] y, [x y,] [y^2]  -- i.e. loop y degree outside, x degree inside.
    basis = np.zeros((ncoeff, size, size), dtype=np.float32)
    basis[0] = 0.5 * (e0 + e1)
    ix = 1
    iy = poldeg + 1
    basis[ix] = 0.5 * (e1 - e0)
    basis[iy] = 0.5 * (e1 - e0)

    polzero = (0.5 * (nx + 1), 0.5 * (ny + 1))
    polscal = (float(nx), float(ny))
    header = [
        {"name": "LOADED", "value": 400, "comment": "Number of loaded sources"},
        {"name": "ACCEPTED", "value": 380, "comment": "Number of accepted sources"},
        {"name": "CHI2", "value": 1.0, "comment": "Final Chi2"},
        {"name": "POLNAXIS", "value": 2, "comment": "Number of context parameters"},
        {"name": "POLGRP1", "value": 1, "comment": "Polynom group for this context parameter"},
        {"name": "POLNAME1", "value": "X_IMAGE", "comment": "Name of this context parameter"},
        {"name": "POLZERO1", "value": polzero[0], "comment": "Offset value for this context"},
        {"name": "POLSCAL1", "value": polscal[0], "comment": "Scale value for this context"},
        {"name": "POLGRP2", "value": 1, "comment": "Polynom group for this context parameter"},
        {"name": "POLNAME2", "value": "Y_IMAGE", "comment": "Name of this context parameter"},
        {"name": "POLZERO2", "value": polzero[1], "comment": "Offset value for this context"},
        {"name": "POLSCAL2", "value": polscal[1], "comment": "Scale value for this context"},
        {"name": "POLNGRP", "value": 1, "comment": "Number of context groups"},
        {"name": "POLDEG1", "value": poldeg, "comment": "Polynom degree for this context group"},
        {"name": "PSF_FWHM", "value": 0.5 * (f0 + f1), "comment": "PSF FWHM"},
        {"name": "PSF_SAMP", "value": float(samp), "comment": "Sampling step of the PSF data"},
        {"name": "PSFNAXIS", "value": 3, "comment": "Dimensionality of the PSF data"},
        {"name": "PSFAXIS1", "value": size, "comment": "Number of element along this axis"},
        {"name": "PSFAXIS2", "value": size, "comment": "Number of element along this axis"},
        {"name": "PSFAXIS3", "value": ncoeff, "comment": "Number of element along this axis"},
    ]
    table = np.zeros(1, dtype=[("PSF_MASK", "f4", (ncoeff, size, size))])
    table["PSF_MASK"][0] = basis
    with fitsio.FITS(str(path), "rw", clobber=True) as fits:
        fits.write(table, extname="PSF_DATA", header=header)
    return PsfexFileInfo(
        path=path,
        size=size,
        samp=float(samp),
        nx=nx,
        ny=ny,
        pixel_scale=pixel_scale,
        fwhm_pix=(f0, f1),
        polzero=polzero,
        polscal=polscal,
        poldeg=poldeg,
    )


def measure_fwhm(image: np.ndarray) -> tuple[float, float]:
    """Size of a star stamp.

    Parameters
    ----------
    image : numpy.ndarray
        2-D stamp (any flux units) with the star near its centre.

    Returns
    -------
    sigma : float
        Adaptive-moment ``sigma`` from ``galsim.hsm.FindAdaptiveMom`` (stamp pixels).
    fwhm : float
        FWHM from ``galsim.Image.calculateFWHM`` about the adaptive-moment centroid (stamp
        pixels; a half-maximum radius from the pixel values, so coarse for undersampled stars).
    """
    im = galsim.Image(np.ascontiguousarray(image, dtype=np.float64), scale=1.0)
    mom = galsim.hsm.FindAdaptiveMom(im)
    # calculateFWHM takes radii from ``center`` (default: the stamp centre), so give it the star.
    fwhm = im.calculateFWHM(center=mom.moments_centroid)
    return float(mom.moments_sigma), float(fwhm)


def _moffat_at(
    x: float, y: float, nx: int, ny: int, fwhm_range: tuple[float, float]
) -> galsim.GSObject:
    """Moffat (world, arcsec) whose FWHM is linear in ``x + y`` (1-based pixels)."""
    t = (x + y - 2.0) / (nx + ny - 2.0)
    fwhm = fwhm_range[0] + t * (fwhm_range[1] - fwhm_range[0])
    return galsim.Moffat(beta=MOFFAT_BETA, fwhm=fwhm)


def build_piff_model(
    path: str | Path,
    *,
    nx: int = 2048,
    ny: int = 4096,
    pixel_scale: float = 0.263,
    fwhm_range: tuple[float, float] = (0.9, 0.96),
    nstars_side: tuple[int, int] = (4, 7),
    stamp_size: int = 25,
    seed: int = 1234,
    wcs: galsim.BaseWCS | None = None,
    chipnum: int = 0,
) -> PiffFileInfo:
    """Fit and write a Piff model whose Moffat FWHM varies linearly across a CCD.

    Noise-free Moffat stars (FWHM linear in ``x + y`` between ``fwhm_range``) are drawn,
    pixel included, on a grid of 1-based positions with random sub-pixel offsets, then fitted
    with a ``piff.SimplePSF`` of a ``piff.Moffat`` model (``beta`` fixed) and a first-order
    ``piff.Polynomial`` interpolation of its parameters in field coordinates ``(u, v)``.
    By default the WCS is a ``galsim.PixelScale`` (no pointing needed); with a celestial
    ``wcs`` the pointing is the sky position of the CCD centre.  Takes about a second.

    Parameters
    ----------
    path : str or pathlib.Path
        Output file (overwritten).
    nx, ny : int, optional
        CCD size (pixels).
    pixel_scale : float, optional
        Pixel scale (arcsec / pixel).
    fwhm_range : tuple of float, optional
        Moffat FWHM (arcsec, before the pixel) at 1-based ``(1, 1)`` and ``(nx, ny)``.
    nstars_side : tuple of int, optional
        Number of stars along x and along y.
    stamp_size : int, optional
        Star stamp side (pixels).
    seed : int, optional
        Seed of the sub-pixel offsets.
    wcs : galsim.BaseWCS, optional
        WCS of the CCD in 1-based image coordinates (e.g. ``galsim.GSFitsWCS`` of a TPV or
        TAN-SIP header); default ``galsim.PixelScale(pixel_scale)``.  The FWHM is in arcsec on
        the sky, so with a real WCS the size in pixels also follows the pixel scale.
    chipnum : int, optional
        Chip number the model is stored under.

    Returns
    -------
    PiffFileInfo
        The file's parameters.
    """
    import piff  # optional test dependency

    path = Path(path)
    if wcs is None:
        wcs = galsim.PixelScale(pixel_scale)
    pointing = None
    if wcs.isCelestial():
        pointing = wcs.toWorld(galsim.PositionD(0.5 * (nx + 1), 0.5 * (ny + 1)))
    rng = np.random.default_rng(seed)
    stars = []
    half = stamp_size // 2
    for yc in np.linspace(1 + half, ny - half, nstars_side[1]):
        for xc in np.linspace(1 + half, nx - half, nstars_side[0]):
            x = float(xc + rng.uniform(-0.5, 0.5))
            y = float(yc + rng.uniform(-0.5, 0.5))
            ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
            bounds = galsim.BoundsI(ix - half, ix + half, iy - half, iy + half)
            image = galsim.ImageD(bounds, wcs=wcs)
            _moffat_at(x, y, nx, ny, fwhm_range).drawImage(image, center=galsim.PositionD(x, y))
            weight = galsim.ImageD(bounds, wcs=wcs, init_value=1.0e6)
            data = piff.StarData(
                image,
                galsim.PositionD(x, y),
                weight=weight,
                pointing=pointing,
                properties={"chipnum": chipnum},
            )
            stars.append(piff.Star(data, None))
    model = piff.Moffat(beta=MOFFAT_BETA)
    interp = piff.Polynomial(order=1)
    psf = piff.SimplePSF(model, interp, outliers=None, max_iter=4)
    psf.set_context({chipnum: wcs}, pointing)
    psf.fit(stars)
    psf.write(str(path))
    return PiffFileInfo(
        path=path,
        nx=nx,
        ny=ny,
        pixel_scale=pixel_scale,
        fwhm_arcsec=fwhm_range,
        origin=1,
        nstars=len(stars),
        chipnum=chipnum,
    )
