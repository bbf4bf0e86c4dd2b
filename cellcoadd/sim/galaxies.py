"""Galaxy populations and drawing of sources through a local WCS Jacobian.

Shapes use the reduced-shear convention (``|e| = (a - b) / (a + b)``) in GalSim's sky
frame (``u`` West, ``v`` North); a galaxy is its intrinsic shape followed by the lensing
shear.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import galsim
import numpy as np

from cellcoadd.errors import CellCoaddValueError
from cellcoadd.geometry.wcs_utils import jacobian_wcs
from cellcoadd.sim.config import GalaxyConfig

#: A user-supplied population: ``sampler(rng, n) -> (mag, hlr)`` arrays (mag at the
#: simulation zero point, hlr in arcsec).
GalaxySampler = Callable[[np.random.Generator, int], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class GalaxyProperties:
    """Drawn properties of ``n`` galaxies (arrays of length n).

    Attributes
    ----------
    mag : ndarray
        Magnitude at the simulation zero point.
    hlr : ndarray
        Half-light radius, arcsec.
    e1, e2 : ndarray
        Intrinsic ellipticity (reduced-shear convention).
    """

    mag: np.ndarray
    hlr: np.ndarray
    e1: np.ndarray
    e2: np.ndarray

    def __len__(self) -> int:
        return len(self.mag)

    def flux(self, zero_point: float) -> np.ndarray:
        """Total counts at ``zero_point``."""
        return mag_to_flux(self.mag, zero_point)


def mag_to_flux(mag: np.ndarray | float, zero_point: float) -> np.ndarray:
    """Counts of magnitude ``mag`` at ``zero_point``: ``10**(-0.4 (mag - zero_point))``."""
    return np.power(10.0, -0.4 * (np.asarray(mag, dtype=float) - zero_point))


def draw_ellipticities(
    rng: np.random.Generator, n: int, sigma_e: float
) -> tuple[np.ndarray, np.ndarray]:
    """Draw ``n`` ellipticities from ``P(e) ~ (1 - e^2)^2 exp(-e^2 / 2 sigma_e^2)``.

    ``P`` is a density in the (e1, e2) plane on the unit disk (the Bernstein & Armstrong
    prior). Rejection sampling: propose ``(e1, e2)`` from the 2-D Gaussian of width
    ``sigma_e`` and accept with probability ``(1 - e^2)^2`` (0 outside the disk).
    """
    if sigma_e == 0.0:
        return np.zeros(n), np.zeros(n)
    e1 = np.empty(n)
    e2 = np.empty(n)
    todo = np.arange(n)
    while todo.size:
        p1 = sigma_e * rng.standard_normal(todo.size)
        p2 = sigma_e * rng.standard_normal(todo.size)
        esq = p1**2 + p2**2
        accept = rng.uniform(size=todo.size) < np.where(esq < 1.0, (1.0 - esq) ** 2, 0.0)
        e1[todo[accept]] = p1[accept]
        e2[todo[accept]] = p2[accept]
        todo = todo[~accept]
    return e1, e2


def draw_galaxy_properties(
    config: GalaxyConfig,
    rng: np.random.Generator,
    n: int,
    sampler: GalaxySampler | None = None,
) -> GalaxyProperties:
    """Draw magnitudes, sizes and intrinsic shapes of ``n`` galaxies.

    Magnitudes are Gaussian (flux log-normal) and sizes log-normal about a
    magnitude-dependent median, both truncated by redrawing (see :class:`GalaxyConfig`),
    unless ``sampler`` supplies ``(mag, hlr)``.
    """
    if sampler is not None:
        mag, hlr = (np.asarray(a, dtype=float) for a in sampler(rng, n))
        if mag.shape != (n,) or hlr.shape != (n,) or not np.all(hlr > 0):
            raise CellCoaddValueError(
                "a galaxy sampler must return n magnitudes and n positive sizes"
            )
    else:
        mag = _truncated_normal(rng, n, config.mag_mean, config.mag_sigma, config)
        median = config.hlr_median * 10.0 ** (config.hlr_mag_slope * (mag - config.mag_mean))
        hlr = np.empty(n)
        todo = np.arange(n)
        while todo.size:
            values = median[todo] * np.exp(config.hlr_ln_sigma * rng.standard_normal(todo.size))
            good = (values >= config.hlr_min) & (values <= config.hlr_max)
            hlr[todo[good]] = values[good]
            todo = todo[~good]
            if config.hlr_ln_sigma == 0.0 and todo.size:
                hlr[todo] = np.clip(median[todo], config.hlr_min, config.hlr_max)
                break
    e1, e2 = draw_ellipticities(rng, n, config.sigma_e)
    return GalaxyProperties(mag=mag, hlr=hlr, e1=e1, e2=e2)


def _truncated_normal(
    rng: np.random.Generator, n: int, mean: float, sigma: float, config: GalaxyConfig
) -> np.ndarray:
    if sigma == 0.0:
        return np.full(n, float(np.clip(mean, config.mag_min, config.mag_max)))
    out = np.empty(n)
    todo = np.arange(n)
    while todo.size:
        values = mean + sigma * rng.standard_normal(todo.size)
        good = (values >= config.mag_min) & (values <= config.mag_max)
        out[todo[good]] = values[good]
        todo = todo[~good]
    return out


def exponential_galaxy(
    flux: float, hlr: float, e1: float, e2: float, g1: float, g2: float
) -> galsim.GSObject:
    """Exponential profile with intrinsic shape ``(e1, e2)`` then lensed by ``(g1, g2)``."""
    profile = galsim.Exponential(half_light_radius=float(hlr), flux=float(flux))
    if e1 != 0.0 or e2 != 0.0:
        profile = profile.shear(g1=float(e1), g2=float(e2))
    if g1 != 0.0 or g2 != 0.0:
        profile = profile.shear(g1=float(g1), g2=float(g2))
    return profile


def draw_source(
    profile: galsim.GSObject,
    image: galsim.Image,
    x: float,
    y: float,
    jacobian: np.ndarray,
    half_size: int,
    method: str = "auto",
) -> None:
    """Add ``profile`` centred at pixel ``(x, y)`` into ``image`` (in place).

    ``image`` must have 0-based bounds (array pixel ``[j, i]`` is position ``(i, j)``).
    The profile is drawn, with the pixel response for ``method="auto"``, through the
    local ``jacobian`` into the square of ``2 half_size + 1`` pixels around the nearest
    pixel, clipped to the image; nothing is drawn if the square misses the image.
    """
    ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
    stamp = galsim.BoundsI(ix - half_size, ix + half_size, iy - half_size, iy + half_size)
    overlap = stamp & image.bounds
    if not overlap.isDefined():
        return
    view = image[overlap]
    profile.drawImage(
        image=view,
        wcs=jacobian_wcs(jacobian),
        method=method,
        center=galsim.PositionD(x, y),
        add_to_image=True,
    )
