"""Field mode: a patch of sky with galaxies and stars observed by a small focal plane.

The sky region is a patch's outer box grown by ``region_margin``; galaxies (as in the
stamp mode, all lensed by ``config.shear``) and stars are placed uniformly over it. Each
visit points the focal plane (:mod:`cellcoadd.sim.focal_plane`) at the patch centre plus a
dither offset, optionally rotated, with its own Moffat PSF (optionally varying over the
focal plane), noise level and zero point. Each CCD becomes one
:class:`~cellcoadd.model.exposure.Exposure` with a TAN (optionally SIP) WCS, a mask with
edge pixels, bad columns and cosmic rays, and Gaussian noise. Objects are drawn only into
stamps around them (never full-CCD FFTs); outside the region a CCD holds noise only.
Everything stays in memory; :func:`cellcoadd.pipelines.simulation_files.write_field_simulation`
writes a :class:`FieldSimulation` to files.

Random streams (all from ``numpy.random.SeedSequence``): ``[seed, 0]`` the catalogue,
``[seed, 1]`` the dithers, ``[seed, 2, visit]`` a visit's PSF, noise level, zero point and
rotation, ``[seed, 3, visit, detector]`` a CCD's noise and defects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import galsim
import numpy as np
from astropy.table import Table
from tqdm import tqdm

from cellcoadd.errors import CellCoaddValueError
from cellcoadd.geometry import Box, SkyMap, SkyMapConfig, Tract
from cellcoadd.geometry.wcs_utils import local_jacobian
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.psf_profiles import VaryingPsf
from cellcoadd.sim.config import SimConfig
from cellcoadd.sim.dither import dither_offsets
from cellcoadd.sim.focal_plane import Detector, FocalPlane, offset_position
from cellcoadd.sim.galaxies import (
    GalaxySampler,
    draw_galaxy_properties,
    draw_source,
    exponential_galaxy,
    mag_to_flux,
)
from cellcoadd.sim.psf import draw_psf_parameters, focal_plane_psf, moffat_psf

#: Demo geometry: 4 x 4 cells of 150 + 2 x 50 pixels at 0.2 arcsec/pixel per patch.
DEMO_SKYMAP_CONFIG = SkyMapConfig(
    pixel_scale=0.2, cell_inner=150, cell_border=50, cells_per_patch=4, patches_per_tract=3
)
DEMO_PATCH = (1, 1)


def demo_skymap(ra: float = 60.0, dec: float = -30.0) -> SkyMap:
    """One tract of 3 x 3 demo patches centred on ``(ra, dec)``; simulate patch (1, 1)."""
    return SkyMap.from_centers([(ra, dec)], DEMO_SKYMAP_CONFIG)


@dataclass(eq=False)
class FieldSimulation:
    """The result of :func:`simulate_field`.

    Attributes
    ----------
    exposures : list of Exposure
        One per (visit, detector), visits in order.
    truth : astropy.table.Table
        One row per object: id, ra, dec (deg), flux (counts at ``config.zero_point``), hlr
        (arcsec, 0 for stars), g1, g2 (applied shear, 0 for stars), is_star, mag, e1, e2
        (intrinsic shape), x, y (tract pixels).
    visits : astropy.table.Table
        One row per visit: visit, ra, dec (boresight, deg), rotation (deg), psf_fwhm,
        psf_g1, psf_g2, noise_sigma, zero_point.
    skymap : SkyMap
    tract_id : int
    patch_index : tuple of int
    config : SimConfig
    seed : int
    """

    exposures: list[Exposure]
    truth: Table
    visits: Table
    skymap: SkyMap
    tract_id: int
    patch_index: tuple[int, int]
    config: SimConfig
    seed: int

    def description(self) -> dict:
        """JSON-able summary: seed, tract, patch, counts and the full configuration."""
        return {
            "seed": self.seed,
            "tract": self.tract_id,
            "patch": list(self.patch_index),
            "n_visits": len(self.visits),
            "n_exposures": len(self.exposures),
            "n_objects": len(self.truth),
            "config": self.config.model_dump(mode="json"),
        }


def simulate_field(
    config: SimConfig,
    skymap: SkyMap,
    tract_id: int,
    patch_index: tuple[int, int],
    n_visits: int,
    seed: int,
    *,
    sampler: GalaxySampler | None = None,
    progress: bool = False,
) -> FieldSimulation:
    """Simulate ``n_visits`` visits of the focal plane over one patch.

    Parameters
    ----------
    config : SimConfig
        Object, PSF and noise distributions; ``config.field`` sets the focal plane, the
        dithers, the PSF variation, densities and defects.
    skymap : SkyMap
        Geometry of the coadd; the patch ``patch_index`` of tract ``tract_id`` is the
        target.
    n_visits : int
        Number of visits.
    seed : int
        Non-negative seed fixing everything.
    sampler : callable, optional
        ``sampler(rng, n) -> (mag, hlr)`` replacing the configured galaxy population.
    progress : bool
        Show a progress bar over visits.
    """
    if n_visits < 0 or seed < 0:
        raise CellCoaddValueError("n_visits and seed must be non-negative", value=(n_visits, seed))
    tract = skymap[tract_id]
    patch = tract.patch(*patch_index)
    truth = _catalogue(config, tract, patch.outer_bbox, seed, sampler)
    galaxies = [
        None
        if row["is_star"]
        else exponential_galaxy(row["flux"], row["hlr"], row["e1"], row["e2"], row["g1"], row["g2"])
        for row in truth
    ]
    box = patch.outer_bbox
    centre = tract.pixel_to_sky(
        (box.x_start + box.x_stop - 1) / 2.0, (box.y_start + box.y_stop - 1) / 2.0
    )
    focal_plane = FocalPlane.from_config(config.field, config.pixel_scale)
    offsets = dither_offsets(
        config.field.dither, n_visits, config.field.dither_radius, _rng(seed, 1), region="disk"
    )
    boresight_ra, boresight_dec = offset_position(
        float(centre[0][0]), float(centre[1][0]), offsets[:, 0], offsets[:, 1]
    )

    exposures: list[Exposure] = []
    visits: list[_Visit] = []
    for visit in tqdm(range(n_visits), desc="visits", disable=not progress):
        conditions = _draw_visit(config, visit, seed, (boresight_ra[visit], boresight_dec[visit]))
        visits.append(conditions)
        for detector in focal_plane.detectors:
            exposures.append(
                _observe_ccd(config, focal_plane, detector, conditions, truth, galaxies, seed)
            )
    names = [f.name for f in fields(_Visit)]
    visit_table = Table(
        rows=[tuple(getattr(v, n) for n in names) for v in visits] or None,
        names=names,
        dtype=[np.int64] + [np.float64] * (len(names) - 1),
    )
    return FieldSimulation(
        exposures=exposures,
        truth=truth,
        visits=visit_table,
        skymap=skymap,
        tract_id=int(tract_id),
        patch_index=(int(patch_index[0]), int(patch_index[1])),
        config=config,
        seed=int(seed),
    )


def _rng(*entropy: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(e) for e in entropy]))


def _catalogue(
    config: SimConfig, tract: Tract, outer_box: Box, seed: int, sampler: GalaxySampler | None
) -> Table:
    """Galaxies and stars placed uniformly over ``outer_box`` grown by the margin."""
    rng = _rng(seed, 0)
    field = config.field
    scale = tract.config.pixel_scale
    region = outer_box.grow(int(math.ceil(field.region_margin / scale)))
    area = region.nx * region.ny * (scale / 60.0) ** 2  # arcmin^2
    n_gal = int(rng.poisson(field.galaxy_density * area))
    n_star = int(rng.poisson(field.star_density * area))
    n = n_gal + n_star
    x = rng.uniform(region.x_start - 0.5, region.x_stop - 0.5, n)
    y = rng.uniform(region.y_start - 0.5, region.y_stop - 0.5, n)
    ra, dec = tract.pixel_to_sky(x, y)
    props = draw_galaxy_properties(config.galaxy, rng, n_gal, sampler)
    star_mag = rng.uniform(field.star_mag_min, field.star_mag_max, n_star)
    is_star = np.concatenate([np.zeros(n_gal, bool), np.ones(n_star, bool)])
    mag = np.concatenate([props.mag, star_mag])
    zeros = np.zeros(n_star)
    g1, g2 = config.shear
    return Table(
        {
            "id": np.arange(n, dtype=np.int64),
            "ra": ra,
            "dec": dec,
            "flux": mag_to_flux(mag, config.zero_point),
            "hlr": np.concatenate([props.hlr, zeros]),
            "g1": np.where(is_star, 0.0, g1),
            "g2": np.where(is_star, 0.0, g2),
            "is_star": is_star,
            "mag": mag,
            "e1": np.concatenate([props.e1, zeros]),
            "e2": np.concatenate([props.e2, zeros]),
            "x": x,
            "y": y,
        }
    )


@dataclass(frozen=True)
class _Visit:
    """Observing conditions of one visit (the rows of ``FieldSimulation.visits``)."""

    visit: int
    ra: float
    dec: float
    rotation: float
    psf_fwhm: float
    psf_g1: float
    psf_g2: float
    noise_sigma: float
    zero_point: float


def _draw_visit(config: SimConfig, visit: int, seed: int, boresight: tuple[float, float]) -> _Visit:
    rng = _rng(seed, 2, visit)
    psf = draw_psf_parameters(config.psf, rng, 1)
    noise_scale = max(0.1, 1.0 + config.field.noise_scatter * rng.standard_normal())
    zero_point = config.zero_point + config.field.zero_point_scatter * rng.standard_normal()
    rotation = rng.uniform(0.0, 360.0) if config.field.rotate else 0.0
    return _Visit(
        visit=int(visit),
        ra=float(boresight[0]),
        dec=float(boresight[1]),
        rotation=float(rotation),
        psf_fwhm=float(psf.fwhm[0]),
        psf_g1=float(psf.g1[0]),
        psf_g2=float(psf.g2[0]),
        noise_sigma=float(config.noise_sigma * noise_scale),
        zero_point=float(zero_point),
    )


def _observe_ccd(
    config: SimConfig,
    focal_plane: FocalPlane,
    detector: Detector,
    visit: _Visit,
    truth: Table,
    galaxies: list[galsim.GSObject | None],
    seed: int,
) -> Exposure:
    """One CCD of one visit: objects, noise, defects, mask."""
    field = config.field
    wcs = focal_plane.detector_wcs(detector, (visit.ra, visit.dec), visit.rotation, field.sip_k)
    base_psf = moffat_psf(visit.psf_fwhm, visit.psf_g1, visit.psf_g2, config.psf.beta)
    psf = focal_plane_psf(
        base_psf,
        focal_plane.boresight_pixel(detector),
        focal_plane.corner_radius,
        field.psf_fwhm_edge,
        field.psf_g_edge,
    )
    image = galsim.Image(np.zeros((detector.ny, detector.nx)), xmin=0, ymin=0)
    x, y = wcs.all_world2pix(truth["ra"], truth["dec"], 0, quiet=True)
    flux_scale = 10.0 ** (0.4 * (visit.zero_point - config.zero_point))
    for k in np.flatnonzero(np.isfinite(x) & np.isfinite(y)):
        half = _half_size(truth["hlr"][k], truth["mag"][k], bool(truth["is_star"][k]), config)
        if not (
            -half <= x[k] <= detector.nx - 1 + half and -half <= y[k] <= detector.ny - 1 + half
        ):
            continue
        psf_here = psf(x[k], y[k]) if isinstance(psf, VaryingPsf) else psf
        flux = float(truth["flux"][k] * flux_scale)
        galaxy = galaxies[k]
        profile = (
            psf_here.withFlux(flux)
            if galaxy is None
            else galsim.Convolve(galaxy.withFlux(flux), psf_here)
        )
        draw_source(profile, image, x[k], y[k], local_jacobian(wcs, x[k], y[k]), half)

    rng = _rng(seed, 3, visit.visit, detector.id)
    noise_sigma = visit.noise_sigma
    pixels = image.array + noise_sigma * rng.standard_normal(image.array.shape)
    bits = MaskBits()
    mask = np.zeros(pixels.shape, dtype=np.int32)
    _add_defects(pixels, mask, bits, rng, field.bad_columns, field.cosmic_rays, noise_sigma)
    edge = field.edge_pixels
    if edge:
        mask[:edge, :] |= bits.value("EDGE")
        mask[-edge:, :] |= bits.value("EDGE")
        mask[:, :edge] |= bits.value("EDGE")
        mask[:, -edge:] |= bits.value("EDGE")
    return Exposure(
        image=pixels.astype(np.float32),
        wcs=wcs,
        variance=noise_sigma**2,
        psf=psf,
        visit=visit.visit,
        detector=int(detector.id),
        band=config.band,
        zero_point=visit.zero_point,
        mask=mask,
        mask_bits=bits,
        valid_box=detector.box.grow(-edge),
    )


def _half_size(hlr: float, mag: float, is_star: bool, config: SimConfig) -> int:
    """Half side of the drawing stamp, pixels: enough for the PSF wings of bright stars."""
    psf_extent = 4.0 * config.psf.fwhm_max
    if is_star:
        extent = psf_extent * (2.0 if mag < 20.0 else 1.25)
    else:
        extent = 5.0 * hlr + psf_extent
    return int(np.clip(math.ceil(extent / config.pixel_scale), 12, 64))


def _add_defects(
    pixels: np.ndarray,
    mask: np.ndarray,
    bits: MaskBits,
    rng: np.random.Generator,
    mean_bad_columns: float,
    mean_cosmic_rays: float,
    noise_sigma: float,
) -> None:
    """Bad (partial) columns set to a constant and short cosmic-ray tracks, both masked."""
    ny, nx = pixels.shape
    for _ in range(int(rng.poisson(mean_bad_columns))):
        column = int(rng.integers(0, nx))
        start = int(rng.integers(0, ny))
        stop = int(rng.integers(start + 1, ny + 1))
        pixels[start:stop, column] = 50.0 * noise_sigma
        mask[start:stop, column] |= bits.value("BAD")
    for _ in range(int(rng.poisson(mean_cosmic_rays))):
        length = int(rng.integers(1, 7))
        angle = rng.uniform(0.0, 2.0 * np.pi)
        x0, y0 = rng.uniform(0, nx - 1), rng.uniform(0, ny - 1)
        steps = np.arange(length)
        cols = np.clip(np.round(x0 + steps * np.cos(angle)).astype(int), 0, nx - 1)
        rows = np.clip(np.round(y0 + steps * np.sin(angle)).astype(int), 0, ny - 1)
        pixels[rows, cols] += rng.uniform(20.0, 300.0, length) * noise_sigma
        mask[rows, cols] |= bits.value("CR")
