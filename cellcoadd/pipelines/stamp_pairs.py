"""One object of the shear-bias validation: simulate a +g/-g pair, coadd, measure.

The paper's stamp simulations (section 3, :mod:`cellcoadd.sim.stamps`) give each object
``n_epochs`` exposures with their own PSF, sub-pixel shift and WCS. For object ``i`` of a
run with seed ``s``:

1. both members of the pair (shear ``+g`` and ``-g``) are simulated noise free from the
   same seed, so they hold the same galaxy, PSFs, shifts and WCSs;
2. the pixel noise level ``sigma`` is the simulation's (``SimConfig.noise_sigma``), or,
   when a target S/N is asked for, ``sigma = sqrt(sum I^2) / snr`` with ``I`` the
   noise-free pixels of the ``+g`` member that are measured (all epochs in coadd mode, the
   first epoch in single mode): the optimal matched-filter S/N of the measured data. A
   range ``(lo, hi)`` draws the target uniformly per object;
3. the same noise fields (unit normals from a generator keyed by ``(s, i)``, scaled by
   ``sigma``) are added to both members;
4. ``coadd`` mode builds cell ``(0, 0)`` of a one-cell sky map centred on the objects
   with the real builder (:func:`cellcoadd.builder.build_cell`, seed ``s``: noise
   realizations keyed by ``(s, epoch, i)``, hence the same for both members) and runs
   metacalibration on it through :func:`~cellcoadd.shear.observation.to_observation`;
   ``single`` mode runs metacalibration on the first epoch alone, with its PSF drawn at
   the object through the epoch's local WCS (pixel response included) and its own noise
   realization (same ``sigma``, independent of the image noise).

Everything about object ``i`` depends only on ``(s, i)`` and the settings, so any split
of a run over processes gives identical results.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from cellcoadd.builder import build_cell
from cellcoadd.builder.kernels.warp import KERNEL_HALF_WIDTH
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.geometry.skymap import SkyMap
from cellcoadd.geometry.tract import Cell
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.exposure import Exposure
from cellcoadd.shear.metacal import METACAL_TYPES, measure_metacal
from cellcoadd.shear.observation import observation_jacobian, to_observation
from cellcoadd.shear.shapes import empty_record
from cellcoadd.sim.config import SimConfig
from cellcoadd.sim.stamps import StampObject, simulate_object

Mode = Literal["coadd", "single"]
MODES: tuple[str, ...] = ("coadd", "single")

#: ``flags`` bit of a measurement that could not be made because the coadd is empty.
NO_COADD = 1 << 8

# Third entry of the per-object generator keys (the simulation itself uses (seed, index)).
_EPOCH_NOISE_STREAM = 1
_SINGLE_NOISE_STREAM = 2
_SNR_STREAM = 3


class ValidationSettings(BaseModel):
    """Everything that fixes the result of a shear-bias validation run (frozen).

    Parameters
    ----------
    mode : {"coadd", "single"}
        Measure the cell coadd of all epochs, or the first epoch alone.
    seed : int
        Seed of the run; object ``i`` depends only on ``(seed, i)``.
    snr : (float, float), optional
        Target optimal S/N range (``lo == hi`` for a fixed S/N); None keeps the
        simulation's noise level ``sim.noise_sigma``.
    step : float
        Metacalibration shear step.
    reconvolution_psf : {"gauss", "fitgauss", "dilate"}
        Metacalibration reconvolution PSF (see :func:`cellcoadd.shear.reconvolution_psf`).
    sim : SimConfig
        Stamp simulation settings (paper defaults: 10 epochs of 48 x 48 pixels at
        0.27 arcsec, ``g = (0.02, 0)``).
    coadd_pixel_scale : float
        Pixel scale of the coadd cell, arcsec.
    cell_inner, cell_border : int
        Cell inner size (odd, so the cell-centre pixel sits exactly on the objects) and
        border, coadd pixels. The outer box plus the Lanczos-3 reach must lie inside every
        epoch's stamp, or epochs are rejected (reported in the results).
    build : BuildConfig
        Builder settings (at least one noise realization: metacal needs it).
    noise_index : int
        Which coadd noise realization feeds the metacal noise correction.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    mode: Mode = "coadd"
    seed: int = Field(0, ge=0)
    snr: tuple[float, float] | None = None
    step: float = Field(0.01, gt=0.0, lt=0.1)
    reconvolution_psf: Literal["gauss", "fitgauss", "dilate"] = "gauss"
    sim: SimConfig = SimConfig()
    coadd_pixel_scale: float = Field(0.2, gt=0.0, description="arcsec/pixel")
    cell_inner: int = Field(None, gt=0, description="coadd pixels")  # type: ignore[assignment]
    cell_border: int = Field(5, ge=0, description="coadd pixels")
    build: BuildConfig = BuildConfig(n_noise=1, psf_size=35)
    noise_index: int = Field(0, ge=0)

    @model_validator(mode="before")
    @classmethod
    def _default_cell(cls, data: object) -> object:
        if isinstance(data, dict) and data.get("cell_inner") is None:
            sim = data.get("sim")
            sim = SimConfig() if sim is None else SimConfig.model_validate(sim)
            data = dict(data)
            data["cell_inner"] = largest_cell_inner(
                sim, data.get("coadd_pixel_scale", 0.2), data.get("cell_border", 5)
            )
        return data

    @field_validator("snr", mode="before")
    @classmethod
    def _snr_pair(cls, value: object) -> object:
        if value is None:
            return None
        if isinstance(value, (tuple, list)):
            return tuple(value) * 2 if len(value) == 1 else value
        return (value, value)  # a single number: fixed S/N

    @model_validator(mode="after")
    def _check(self) -> ValidationSettings:
        if self.snr is not None and not 0.0 < self.snr[0] <= self.snr[1]:
            raise ValueError(f"snr must satisfy 0 < lo <= hi, got {self.snr}")
        if self.cell_inner % 2 == 0:
            raise ValueError(
                f"cell_inner must be odd so the cell centre falls on the objects, "
                f"got {self.cell_inner}"
            )
        if self.build.n_noise <= self.noise_index:
            raise ValueError(
                f"build.n_noise = {self.build.n_noise} has no noise realization "
                f"{self.noise_index}: metacal needs one"
            )
        if self.sim.shear[0] == 0.0 or self.sim.shear[1] != 0.0:
            raise ValueError(
                f"the bias is measured on g1: sim.shear must be (g, 0) with g != 0, "
                f"got {self.sim.shear}"
            )
        if self.build.psf_size > self.cell_inner + 2 * self.cell_border:
            raise ValueError("build.psf_size exceeds the cell outer box")
        return self

    def skymap_config(self) -> SkyMapConfig:
        """One tract of one patch of one cell, centred on the stamp objects."""
        return SkyMapConfig(
            pixel_scale=self.coadd_pixel_scale,
            cell_inner=self.cell_inner,
            cell_border=self.cell_border,
            cells_per_patch=1,
            patches_per_tract=1,
            patch_border_cells=0,
        )


def largest_cell_inner(sim: SimConfig, coadd_pixel_scale: float, cell_border: int = 5) -> int:
    """Largest odd cell inner size whose outer box fits every epoch stamp with Lanczos-3.

    Lanczos-3 taps run from ``floor(x) - 2`` to ``floor(x) + 3``, so every outer-box pixel
    centre must map to ``2 <= x < stamp_size - 3`` in each epoch; the object sits at
    ``(stamp_size - 1) / 2`` plus a shift of up to ``max_shift``. The outer box's
    half-width, in exposure pixels, is stretched by up to ``|ds| + |eta1| + |eta2|`` by the
    per-epoch WCS variation; six times the combined standard deviation of those (no
    rotation) keeps rejections negligible. With rotations the box corner can point
    anywhere, so a factor ``sqrt(2)`` more is kept. Defaults: 41 at 0.2 arcsec, 29 at
    0.27 arcsec.

    Raises
    ------
    ValueError
        If not even a one-pixel inner region fits.
    """
    # taps floor(x) - (w - 1) .. floor(x) + w must stay in [0, stamp_size)
    reach = (sim.stamp_size - 1) / 2.0 - sim.max_shift - (KERNEL_HALF_WIDTH - 1)
    spread = np.sqrt(sim.wcs.scale_sigma**2 + 2.0 * sim.wcs.shear_sigma**2)
    stretch = (1.0 + 6.0 * spread) * (np.sqrt(2.0) if sim.wcs.rotate else 1.0)
    half_outer = int(np.floor(reach / stretch * sim.pixel_scale / coadd_pixel_scale - 1e-9))
    inner = 2 * (half_outer - cell_border) + 1
    if inner < 1:
        raise ValueError(
            f"no cell with a {cell_border}-pixel border at {coadd_pixel_scale} arcsec/pixel "
            f"fits in a {sim.stamp_size}-pixel stamp"
        )
    return inner


def stamp_cell(settings: ValidationSettings) -> Cell:
    """Cell ``(0, 0)`` of the one-cell sky map centred on the objects; its centre pixel
    ``(nx // 2, ny // 2)`` of the outer box is exactly at ``(sim.ra, sim.dec)``.

    One cell serves every object, since they all share the sky position."""
    skymap = SkyMap.from_centers([(settings.sim.ra, settings.sim.dec)], settings.skymap_config())
    return skymap[0].cell(0, 0)


@dataclass(frozen=True, eq=False)
class PairMeasurement:
    """Metacal measurements of one object sheared by ``+g`` and by ``-g``.

    Attributes
    ----------
    index : int
        Object index.
    plus, minus : dict of str to ndarray
        For each metacal type, a length-1 array of
        :data:`~cellcoadd.shear.metacal.SHAPE_DTYPE`.
    noise_sigma : float
        Pixel noise standard deviation of the epochs, counts.
    snr : float
        Target optimal S/N (NaN when the simulation's noise level was kept).
    n_inputs : int
        Epochs used in the coadd (1 in single mode).
    cpu_seconds : float
        CPU time spent on this object (simulation, coaddition, measurement).
    """

    index: int
    plus: dict[str, np.ndarray]
    minus: dict[str, np.ndarray]
    noise_sigma: float
    snr: float
    n_inputs: int
    cpu_seconds: float


def _generator(settings: ValidationSettings, index: int, stream: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([settings.seed, int(index), stream]))


def _target_snr(settings: ValidationSettings, index: int) -> float:
    if settings.snr is None:
        return float("nan")
    low, high = settings.snr
    return float(_generator(settings, index, _SNR_STREAM).uniform(low, high))


def _noise_sigma(settings: ValidationSettings, obj: StampObject, snr: float) -> float:
    if not np.isfinite(snr):
        return float(settings.sim.noise_sigma)
    epochs = obj.exposures[:1] if settings.mode == "single" else obj.exposures
    signal = float(np.sqrt(sum(np.sum(np.square(e.image)) for e in epochs)))
    return signal / snr


def _with_noise(obj: StampObject, noise: np.ndarray, sigma: float) -> list[Exposure]:
    return [
        dataclasses.replace(exposure, image=exposure.image + sigma * plane, variance=sigma**2)
        for exposure, plane in zip(obj.exposures, noise, strict=True)
    ]


def _failed(flags: int) -> dict[str, np.ndarray]:
    return {name: empty_record(flags) for name in METACAL_TYPES}


def _measure_coadd(
    settings: ValidationSettings, cell: Cell, exposures: list[Exposure]
) -> tuple[dict[str, np.ndarray], int]:
    coadd = build_cell(cell, exposures, settings.build, seed=settings.seed)
    if coadd.is_empty:
        return _failed(NO_COADD), 0
    obs = to_observation(coadd, noise_index=settings.noise_index)
    jac = obs["jacobian"]
    result = measure_metacal(
        obs["image"],
        obs["psf"]["image"],
        obs["noise"],
        observation_jacobian(obs),
        noise_sigma=float(np.sqrt(obs["meta"]["noise_variance"])),
        step=settings.step,
        psf=settings.reconvolution_psf,
        guess_centroid=(jac["col0"], jac["row0"]),
    )
    return result, coadd.n_used


def epoch_psf_image(exposure: Exposure, x: float, y: float, size: int) -> np.ndarray:
    """The PSF of ``exposure`` at pixel ``(x, y)`` on an odd ``size`` x ``size`` stamp.

    Drawn through the exposure's local jacobian at ``(x, y)``, with the pixel response,
    centred on the stamp's central pixel: the form metacal takes.
    """
    centre = float(size // 2)
    return exposure.draw_psf(x, y, Box.from_shape((size, size)), center=(centre, centre))


def _measure_single(
    settings: ValidationSettings, obj: StampObject, exposure: Exposure, sigma: float
) -> dict[str, np.ndarray]:
    x, y = obj.epochs[0].position
    noise = sigma * _generator(settings, obj.index, _SINGLE_NOISE_STREAM).standard_normal(
        exposure.shape
    )
    return measure_metacal(
        exposure.image,
        epoch_psf_image(exposure, x, y, settings.build.psf_size),
        noise,
        exposure.local_jacobian(x, y),
        noise_sigma=sigma,
        step=settings.step,
        psf=settings.reconvolution_psf,
        guess_centroid=(x, y),
    )


def measure_pair(
    settings: ValidationSettings, index: int, cell: Cell | None = None
) -> PairMeasurement:
    """Simulate object ``index`` sheared by ``+g`` and ``-g`` and measure both members.

    See the module docstring for the procedure. ``cell`` is :func:`stamp_cell` of the
    settings (made here when not given; pass it to reuse it across objects).
    """
    start = time.process_time()
    if settings.mode == "coadd" and cell is None:
        cell = stamp_cell(settings)
    g1, g2 = settings.sim.shear
    plus = simulate_object(settings.sim, settings.seed, index, (g1, g2), add_noise=False)
    minus = simulate_object(settings.sim, settings.seed, index, (-g1, -g2), add_noise=False)
    snr = _target_snr(settings, index)
    sigma = _noise_sigma(settings, plus, snr)
    size = settings.sim.stamp_size
    noise = _generator(settings, index, _EPOCH_NOISE_STREAM).standard_normal(
        (len(plus.exposures), size, size)
    )
    results = []
    n_inputs = 1
    for obj in (plus, minus):
        exposures = _with_noise(obj, noise, sigma)
        if settings.mode == "coadd":
            assert cell is not None  # made above
            measured, n_inputs = _measure_coadd(settings, cell, exposures)
        else:
            measured = _measure_single(settings, obj, exposures[0], sigma)
        results.append(measured)
    return PairMeasurement(
        index=int(index),
        plus=results[0],
        minus=results[1],
        noise_sigma=sigma,
        snr=snr,
        n_inputs=n_inputs,
        cpu_seconds=time.process_time() - start,
    )


__all__ = [
    "MODES",
    "NO_COADD",
    "PairMeasurement",
    "ValidationSettings",
    "epoch_psf_image",
    "largest_cell_inner",
    "measure_pair",
    "stamp_cell",
]
