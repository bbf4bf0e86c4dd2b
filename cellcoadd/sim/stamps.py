"""Stamp mode: isolated galaxies observed in several epochs (the paper's section 3).

Each object is an exponential galaxy, lensed by a constant shear, observed in
``n_epochs`` epochs on ``stamp_size`` x ``stamp_size`` stamps. Every epoch has its own
Moffat PSF, sub-pixel shift and WCS Jacobian; the stamp's TAN WCS is centred on the
object's sky position, and GalSim draws the galaxy through the local Jacobian of that very
WCS, so image and WCS agree exactly. Pixel noise is Gaussian and uniform.

Everything about object ``i`` is drawn from ``numpy.random.SeedSequence([seed, i])`` in a
fixed order that does not depend on the shear: two runs with the same seed and opposite
shears are a matched pair (same galaxies, PSFs, shifts, WCSs and noise).

Exposure identity: ``visit`` is the epoch number, ``detector`` the object index, so
builders that seed noise realizations from ``(visit, detector)`` give different objects
different noise and the two members of a pair the same.

Everything stays in memory; :func:`cellcoadd.pipelines.simulation_files.write_stamps`
writes the objects to files.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import galsim
import numpy as np
from astropy.table import Table

from cellcoadd.errors import CellCoaddValueError
from cellcoadd.geometry.wcs_utils import canonical_wcs, local_jacobian, tan_wcs
from cellcoadd.model.exposure import Exposure
from cellcoadd.sim.config import SimConfig, WcsVariationConfig
from cellcoadd.sim.galaxies import (
    GalaxySampler,
    draw_galaxy_properties,
    draw_source,
    exponential_galaxy,
    mag_to_flux,
)
from cellcoadd.sim.psf import draw_psf_parameters, psf_profiles


@dataclass(frozen=True)
class StampTruth:
    """What was simulated for one object.

    Attributes
    ----------
    mag, flux : float
        Magnitude and total counts at the configured zero point.
    hlr : float
        Half-light radius, arcsec.
    e1, e2 : float
        Intrinsic ellipticity (reduced-shear convention).
    g1, g2 : float
        Applied shear.
    """

    mag: float
    flux: float
    hlr: float
    e1: float
    e2: float
    g1: float
    g2: float


@dataclass(frozen=True)
class EpochTruth:
    """What was simulated for one epoch of one object.

    Attributes
    ----------
    psf_fwhm, psf_g1, psf_g2 : float
        Moffat FWHM (arcsec, before shearing) and shape of the PSF.
    shift : tuple of float
        Sub-pixel shift of the object from the stamp centre, pixels.
    position : tuple of float
        0-based pixel position of the object centre in the stamp.
    jacobian : ndarray
        Designed WCS Jacobian ``[[du/dx, du/dy], [dv/dx, dv/dy]]``, arcsec/pixel.
    noise_sigma : float
        Pixel noise standard deviation, counts.
    """

    psf_fwhm: float
    psf_g1: float
    psf_g2: float
    shift: tuple[float, float]
    position: tuple[float, float]
    jacobian: np.ndarray
    noise_sigma: float


@dataclass(eq=False)
class StampObject:
    """One simulated object: its epochs as :class:`Exposure` objects and its truth.

    Attributes
    ----------
    index : int
        Object index (the ``detector`` of its exposures).
    ra, dec : float
        Sky position of the galaxy centre, deg.
    exposures : list of Exposure
        One per epoch; each ``psf`` is the epoch's pre-pixel GalSim profile (arcsec).
    truth : StampTruth
        Galaxy properties and shear.
    epochs : list of EpochTruth
        Per-epoch PSF, shift, position, Jacobian and noise.
    galaxy : galsim.GSObject
        The lensed galaxy before the PSF (arcsec, sky frame).
    """

    index: int
    ra: float
    dec: float
    exposures: list[Exposure]
    truth: StampTruth
    epochs: list[EpochTruth]
    galaxy: galsim.GSObject

    @property
    def sky_position(self) -> tuple[float, float]:
        """``(ra, dec)`` of the galaxy centre, deg."""
        return (self.ra, self.dec)

    @property
    def psfs(self) -> list[galsim.GSObject]:
        """The epochs' PSFs (pre-pixel, arcsec)."""
        return [exposure.psf for exposure in self.exposures]


def epoch_jacobians(
    config: WcsVariationConfig, pixel_scale: float, rng: np.random.Generator, n: int
) -> np.ndarray:
    """Draw ``n`` WCS Jacobians (arcsec/pixel), shape (n, 2, 2); see WcsVariationConfig.

    The random numbers drawn do not depend on the switches (a rotation angle is drawn even
    when ``rotate`` is off), so changing one leaves the other quantities unchanged.
    """
    scale = 1.0 + config.scale_sigma * rng.standard_normal(n)
    eta1 = config.shear_sigma * rng.standard_normal(n)
    eta2 = config.shear_sigma * rng.standard_normal(n)
    theta = rng.uniform(0.0, 2.0 * np.pi, n)
    if not config.rotate:
        theta = np.zeros(n)
    out = np.empty((n, 2, 2))
    for k in range(n):
        c, s = np.cos(theta[k]), np.sin(theta[k])
        rotation = np.array([[c, -s], [s, c]])
        distortion = np.array([[1.0 + eta1[k], eta2[k]], [eta2[k], 1.0 - eta1[k]]])
        out[k] = pixel_scale * scale[k] * rotation @ distortion
    return out


def simulate_object(
    config: SimConfig,
    seed: int,
    index: int,
    shear: tuple[float, float] | None = None,
    *,
    add_noise: bool = True,
    sampler: GalaxySampler | None = None,
    rotate_shape: bool = False,
) -> StampObject:
    """Simulate object ``index`` of the run with ``seed`` (see the module docstring).

    ``rotate_shape`` turns the intrinsic ellipticity by 90 degrees (``e -> -e``) and
    changes nothing else (same random numbers: flux, size, PSFs, shifts, WCSs, noise): the
    ring partner that cancels the object's intrinsic shape in a mean.
    """
    shears = [config.shear if shear is None else (float(shear[0]), float(shear[1]))]
    (obj,) = simulate_sheared(
        config, seed, index, shears, add_noise=add_noise, sampler=sampler,
        rotate_shape=rotate_shape,
    )  # fmt: skip
    return obj


def simulate_sheared(
    config: SimConfig,
    seed: int,
    index: int,
    shears: Sequence[tuple[float, float]],
    *,
    add_noise: bool = True,
    sampler: GalaxySampler | None = None,
    rotate_shape: bool = False,
) -> list[StampObject]:
    """Object ``index`` of the run with ``seed`` under each of ``shears``: the same as
    :func:`simulate_object` for each shear, made once for all of them.

    The random draws, PSFs and WCSs are made once; each epoch's WCS object (in canonical
    form, :func:`~cellcoadd.geometry.wcs_utils.canonical_wcs`) is shared by the members'
    exposures, so a ``+g``/``-g`` pair converts each WCS once instead of twice.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))
    n_epochs, size = config.n_epochs, config.stamp_size

    props = draw_galaxy_properties(config.galaxy, rng, 1, sampler)
    psf_params = draw_psf_parameters(config.psf, rng, n_epochs)
    shifts = rng.uniform(-config.max_shift, config.max_shift, (n_epochs, 2))
    jacobians = epoch_jacobians(config.wcs, config.pixel_scale, rng, n_epochs)
    noise = rng.standard_normal((n_epochs, size, size))

    flux = float(mag_to_flux(props.mag[0], config.zero_point))
    turn = -1.0 if rotate_shape else 1.0
    truths = [
        StampTruth(
            mag=float(props.mag[0]),
            flux=flux,
            hlr=float(props.hlr[0]),
            e1=turn * float(props.e1[0]),
            e2=turn * float(props.e2[0]),
            g1=float(g1),
            g2=float(g2),
        )
        for g1, g2 in shears
    ]
    galaxies = [exponential_galaxy(flux, t.hlr, t.e1, t.e2, t.g1, t.g2) for t in truths]
    centre = (size - 1) / 2.0
    exposures: list[list[Exposure]] = [[] for _ in shears]
    epochs = []
    for epoch, psf in enumerate(psf_profiles(config.psf, psf_params)):
        x, y = centre + shifts[epoch, 0], centre + shifts[epoch, 1]
        wcs = tan_wcs(config.ra, config.dec, x, y, jacobians[epoch])
        # GalSim draws through the Jacobian of the WCS as made (as the module says); the
        # exposures hold its canonical form, made once for all members
        jacobian = local_jacobian(wcs, x, y)
        shared_wcs = canonical_wcs(wcs)
        for member, galaxy in zip(exposures, galaxies, strict=True):
            image = galsim.Image(np.zeros((size, size)), xmin=0, ymin=0)
            draw_source(galsim.Convolve(galaxy, psf), image, x, y, jacobian, half_size=size)
            pixels = image.array
            if add_noise:
                pixels = pixels + config.noise_sigma * noise[epoch]
            member.append(
                Exposure(
                    image=pixels,
                    wcs=shared_wcs,
                    variance=config.noise_sigma**2,
                    psf=psf,
                    visit=epoch,
                    detector=int(index),
                    band=config.band,
                    zero_point=config.zero_point,
                    wcs_is_canonical=True,
                )
            )
        epochs.append(
            EpochTruth(
                psf_fwhm=float(psf_params.fwhm[epoch]),
                psf_g1=float(psf_params.g1[epoch]),
                psf_g2=float(psf_params.g2[epoch]),
                shift=(float(shifts[epoch, 0]), float(shifts[epoch, 1])),
                position=(float(x), float(y)),
                jacobian=jacobians[epoch],
                noise_sigma=config.noise_sigma,
            )
        )
    return [
        StampObject(
            index=int(index),
            ra=config.ra,
            dec=config.dec,
            exposures=member,
            truth=truth,
            epochs=list(epochs),
            galaxy=galaxy,
        )
        for member, truth, galaxy in zip(exposures, truths, galaxies, strict=True)
    ]


def simulate_stamps(
    config: SimConfig,
    n_objects: int,
    seed: int,
    shear: tuple[float, float] | None = None,
    *,
    add_noise: bool = True,
    sampler: GalaxySampler | None = None,
    first_index: int = 0,
) -> list[StampObject]:
    """Simulate objects ``first_index`` .. ``first_index + n_objects - 1``.

    Parameters
    ----------
    config : SimConfig
        Distributions (paper defaults).
    n_objects : int
        Number of objects.
    seed : int
        Non-negative seed; with the object index it fixes everything.
    shear : tuple of float, optional
        ``(g1, g2)`` overriding ``config.shear`` (e.g. its negative for a matched pair).
    add_noise : bool
        False for noise-free images (the variance still reports the configured noise).
    sampler : callable, optional
        ``sampler(rng, n) -> (mag, hlr)`` replacing the configured size/flux distribution.
    first_index : int
        Index of the first object (to split a run into chunks that give the same objects).

    Returns
    -------
    list of StampObject
    """
    if n_objects < 0 or seed < 0:
        raise CellCoaddValueError(
            "n_objects and seed must be non-negative", value=(n_objects, seed)
        )
    return [
        simulate_object(config, seed, index, shear, add_noise=add_noise, sampler=sampler)
        for index in range(first_index, first_index + n_objects)
    ]


def simulate_stamp_pair(
    config: SimConfig, n_objects: int, seed: int, **kwargs: object
) -> tuple[list[StampObject], list[StampObject]]:
    """Matched pair: the same objects sheared by ``+config.shear`` and ``-config.shear``."""
    g1, g2 = config.shear
    plus = simulate_stamps(config, n_objects, seed, (g1, g2), **kwargs)  # type: ignore[arg-type]
    minus = simulate_stamps(config, n_objects, seed, (-g1, -g2), **kwargs)  # type: ignore[arg-type]
    return plus, minus


def stamps_truth_tables(objects: list[StampObject]) -> tuple[Table, Table]:
    """Truth of stamp objects as tables: one row per object, one row per epoch.

    The object table has index, ra, dec, mag, flux, hlr, e1, e2, g1, g2; the epoch table
    has index, epoch, psf_fwhm, psf_g1, psf_g2, shift_x, shift_y, x, y, the Jacobian
    (dudx, dudy, dvdx, dvdy, arcsec/pixel) and noise_sigma.
    """
    object_rows = [
        (o.index, o.ra, o.dec, *(getattr(o.truth, f) for f in _TRUTH_FIELDS)) for o in objects
    ]
    objects_table = Table(
        rows=object_rows or None,
        names=("index", "ra", "dec", *_TRUTH_FIELDS),
        dtype=(np.int64,) + (np.float64,) * (2 + len(_TRUTH_FIELDS)),
    )
    epoch_rows = [
        (
            o.index,
            k,
            e.psf_fwhm,
            e.psf_g1,
            e.psf_g2,
            *e.shift,
            *e.position,
            *np.asarray(e.jacobian).ravel(),
            e.noise_sigma,
        )
        for o in objects
        for k, e in enumerate(o.epochs)
    ]
    epoch_names = ("psf_fwhm", "psf_g1", "psf_g2", "shift_x", "shift_y", "x", "y")
    epochs_table = Table(
        rows=epoch_rows or None,
        names=("index", "epoch", *epoch_names, "dudx", "dudy", "dvdx", "dvdy", "noise_sigma"),
        dtype=(np.int64, np.int64) + (np.float64,) * 12,
    )
    return objects_table, epochs_table


_TRUTH_FIELDS = ("mag", "flux", "hlr", "e1", "e2", "g1", "g2")
