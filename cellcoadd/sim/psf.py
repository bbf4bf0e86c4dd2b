"""Per-epoch PSFs of the simulations: Moffat profiles with drawn size and shape.

All PSFs are pre-pixel GalSim profiles in arcsec on the local tangent plane (``u`` West,
``v`` North), as :class:`~cellcoadd.model.exposure.Exposure` expects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import galsim
import numpy as np

from cellcoadd.errors import CellCoaddRuntimeError
from cellcoadd.model.psf_profiles import VaryingPsf
from cellcoadd.sim.config import PsfConfig


@dataclass(frozen=True)
class PsfParameters:
    """Drawn PSF parameters of one or more epochs (arrays of equal length).

    Attributes
    ----------
    fwhm : ndarray
        Moffat FWHM, arcsec.
    g1, g2 : ndarray
        PSF shape, reduced-shear convention.
    """

    fwhm: np.ndarray
    g1: np.ndarray
    g2: np.ndarray

    def __len__(self) -> int:
        return len(self.fwhm)


def lognormal_parameters(mean: float, sigma: float) -> tuple[float, float]:
    """``(mu, s)`` of ln(X) for a log-normal X with the given mean and standard deviation."""
    s2 = math.log1p((sigma / mean) ** 2)
    return math.log(mean) - 0.5 * s2, math.sqrt(s2)


def truncated_lognormal(
    rng: np.random.Generator, n: int, mean: float, sigma: float, low: float, high: float
) -> np.ndarray:
    """``n`` log-normal draws (mean ``mean``, std ``sigma``) redrawn until in [low, high]."""
    mu, s = lognormal_parameters(mean, sigma)
    out = np.empty(n)
    todo = np.arange(n)
    for _ in range(10_000):
        if todo.size == 0:
            return out
        values = rng.lognormal(mu, s, todo.size)
        good = (values >= low) & (values <= high)
        out[todo[good]] = values[good]
        todo = todo[~good]
    raise CellCoaddRuntimeError(f"log-normal({mean}, {sigma}) rarely falls in [{low}, {high}]")


def draw_psf_parameters(config: PsfConfig, rng: np.random.Generator, n: int) -> PsfParameters:
    """Draw ``n`` PSFs: truncated log-normal FWHM, Gaussian shape (see :class:`PsfConfig`)."""
    if config.fwhm_sigma > 0:
        fwhm = truncated_lognormal(
            rng, n, config.fwhm_mean, config.fwhm_sigma, config.fwhm_min, config.fwhm_max
        )
    else:
        fwhm = np.full(n, config.fwhm_mean)
    g1 = config.g1_mean + config.g_sigma * rng.standard_normal(n)
    g2 = config.g2_mean + config.g_sigma * rng.standard_normal(n)
    return PsfParameters(fwhm=fwhm, g1=g1, g2=g2)


def moffat_psf(fwhm: float, g1: float, g2: float, beta: float) -> galsim.GSObject:
    """Unit-flux Moffat PSF of ``fwhm`` arcsec (before shearing) sheared by ``(g1, g2)``."""
    profile = galsim.Moffat(beta=beta, fwhm=float(fwhm))
    if g1 != 0.0 or g2 != 0.0:
        profile = profile.shear(g1=float(g1), g2=float(g2))
    return profile


def psf_profiles(config: PsfConfig, params: PsfParameters) -> list[galsim.GSObject]:
    """The Moffat profiles of drawn :class:`PsfParameters`."""
    return [
        moffat_psf(f, a, b, config.beta)
        for f, a, b in zip(params.fwhm, params.g1, params.g2, strict=True)
    ]


def focal_plane_psf(
    base: galsim.GSObject,
    boresight_xy: tuple[float, float],
    corner_radius: float,
    fwhm_edge: float,
    g_edge: float,
) -> galsim.GSObject | VaryingPsf:
    """The PSF of one CCD when it varies over the focal plane.

    The size grows quadratically with the distance ``r`` from the boresight, by a factor
    ``1 + fwhm_edge`` at ``r = corner_radius``; a radial shear pattern
    ``(g1, g2) = g_edge (xn^2 - yn^2, 2 xn yn)`` (``xn = dx / corner_radius``) reaches
    ``|g| = g_edge`` there. Both zero: the constant ``base``.

    Parameters
    ----------
    base : galsim.GSObject
        The visit's PSF at the boresight.
    boresight_xy : tuple of float
        Boresight position in this CCD's pixel coordinates (0-based; off the CCD in
        general).
    corner_radius : float
        Distance from the boresight to the focal-plane corner, pixels.
    """
    if fwhm_edge == 0.0 and g_edge == 0.0:
        return base
    x0, y0 = boresight_xy
    ln_size = math.log1p(fwhm_edge)
    dilation = ((2, 0, ln_size), (0, 2, ln_size)) if fwhm_edge else ()
    g1 = ((2, 0, g_edge), (0, 2, -g_edge)) if g_edge else ()
    g2 = ((1, 1, 2.0 * g_edge),) if g_edge else ()
    return VaryingPsf(
        base=base,
        x0=float(x0),
        y0=float(y0),
        radius=float(corner_radius),
        dilation=dilation,
        g1=g1,
        g2=g2,
    )
