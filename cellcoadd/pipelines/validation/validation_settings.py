"""Settings of the paired-simulation shear validation
(:mod:`cellcoadd.pipelines.validation.stamp_pairs`,
:mod:`cellcoadd.pipelines.validation.shear_validation`), and the cell the stamps are coadded
into."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from cellcoadd.builder.kernels.warp import KERNEL_HALF_WIDTH
from cellcoadd.errors import ConfigError
from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.geometry.skymap import SkyMap
from cellcoadd.geometry.tract import Cell
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.shear.bfd import DEFAULT_OVERSAMPLE
from cellcoadd.shear.shapes import WMOM_FWHM
from cellcoadd.sim.config import SimConfig

Mode = Literal["coadd", "single", "multi-epoch"]
MODES: tuple[str, ...] = ("coadd", "single", "multi-epoch")
Method = Literal["metacal", "bfd", "anacal"]
METHODS: tuple[str, ...] = ("metacal", "bfd", "anacal")
#: Modes each method runs in.
METHOD_MODES: dict[str, tuple[str, ...]] = {
    "metacal": MODES,
    "bfd": MODES,
    "anacal": ("coadd", "single"),
}


#: Default k-space oversampling of the BFD moments (``bfd_oversample``): the library's.
BFD_OVERSAMPLE = DEFAULT_OVERSAMPLE


def check_method_mode(method: str, mode: str, reconvolution_psf: str = "gauss") -> None:
    """Refuse a method, mode and reconvolution PSF that cannot run together.

    Raises
    ------
    ConfigError
        An unknown method or mode, AnaCal in multi-epoch mode (AnaCal measures one image;
        it has no joint multi-epoch estimator), or multi-epoch metacalibration with the
        ``"dilate"`` reconvolution PSF (each epoch's dilated PSF differs: there is no
        common one).
    """
    if method not in METHOD_MODES:
        raise ConfigError(f"unknown method {method!r}; known: {METHODS}")
    if mode not in MODES:
        raise ConfigError(f"unknown mode {mode!r}; known: {MODES}")
    if mode not in METHOD_MODES[method]:
        raise ConfigError(
            f"method {method!r} runs in mode {' or '.join(METHOD_MODES[method])}, not "
            f"{mode!r}: AnaCal measures one image (a coadd or a single epoch) and has no "
            "joint multi-epoch estimator"
        )
    if method == "metacal" and mode == "multi-epoch" and reconvolution_psf == "dilate":
        raise ConfigError(
            "multi-epoch metacalibration reconvolves every epoch with one round PSF: "
            "reconvolution_psf must be 'gauss' or 'fitgauss', not 'dilate'"
        )


class ValidationSettings(BaseModel):
    """Everything that fixes the result of a shear-bias validation run (frozen).

    Parameters
    ----------
    mode : {"coadd", "single", "multi-epoch"}
        Measure the cell coadd of all epochs, the first epoch alone, or all epochs jointly
        in their own pixels (metacal and BFD; see
        :mod:`cellcoadd.pipelines.validation.epoch_measurements`).
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
        Builder settings (at least one noise realization: metacal needs it). Its
        ``psf_size`` left out becomes the largest odd size the cell's outer box holds, up
        to the builder's default (:meth:`BuildConfig.resolved`): 51 pixels for the
        default stamps (it was 35, which cut 1e-3 of the simulator's PSF flux and biased
        BFD on coadds by +8e-4).
    noise_index : int
        Which coadd noise realization feeds the metacal noise correction.
    method : {"metacal", "bfd", "anacal"}
        Shear method (``anacal``: FPFS through AnaCal, the optional ``cellcoadd[anacal]``,
        in coadd or single mode).
    shape : {"admom", "wmom"}
        Metacal shape: adaptive moments or fixed-weight Gaussian moments.
    wmom_fwhm : float
        FWHM of the ``wmom`` weight, arcsec.
    rotated_partners : bool
        Objects ``2k + 1`` are 90-degree-rotated partners of objects ``2k``.
    bfd_sigma : float
        Scale (arcsec) of the BFD k-sigma weight (N = 4; the paper: 1).
    bfd_templates : int
        Deep templates of the BFD prior (same simulation, noise / 100, shear 0).
    bfd_oversample : int
        k-space oversampling of the BFD moments (zero-padding factor of the images; see
        :func:`cellcoadd.shear.bfd.fourier_data`). Default :data:`BFD_OVERSAMPLE` (4):
        on the FFT grid of the stamp or cell itself (1) the shear derivatives of small
        galaxies are wrong by up to tens of per cent (m1 = -0.027 +- 0.009 in the high-S/N
        check); 4 agrees with 8 to ~1e-5 in m1, at ~16 times the prior's k samples.
    bfd_template_sample : {"independent", "targets"}
        The BFD templates: ``bfd_templates`` objects of an independent sample, or the
        targets themselves unsheared (a prior that is exactly the targets' population:
        the high-S/N check of docs/validation.md).
    bfd_mirror : bool
        Add each template copy's mirror image to the BFD prior (half weight each:
        ``TemplatePrior.from_templates(..., mirror=True)``), making it parity-symmetric.
        Off by default: on the simulated (elliptical exponential) galaxies it moves m1,
        c1, c2 by < 5e-5 and leaves the prior's sampling noise as it is, at twice the
        cost of ``P, Q, R`` (docs/validation.md, "Mirror images in the prior").
    anacal_sigma : float
        Scale (arcsec) of AnaCal's FPFS shapelet kernel.
    object_offset : float
        Coadd mode: each object at a random position of the cell, uniform in the square of
        half-side ``object_offset`` coadd pixels about the cell centre (ring partners
        share it), measured with the PSF the library serves there
        (:meth:`~cellcoadd.model.cell_coadd.CellCoadd.psf_at`: the build gets
        ``psf_phase``); 0 (default): on the cell-centre pixel, where ``cell.psf`` was
        drawn. The cell keeps its size: :func:`stamp_size_for_offset` gives stamps large
        enough (``validate_shear`` enlarges the default ones).
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
    build: BuildConfig = BuildConfig(n_noise=1)
    noise_index: int = Field(0, ge=0)
    method: Method = "metacal"
    shape: Literal["admom", "wmom"] = "admom"
    wmom_fwhm: float = Field(WMOM_FWHM, gt=0.0, description="arcsec")
    rotated_partners: bool = True
    bfd_sigma: float = Field(1.0, gt=0.0, description="arcsec")
    bfd_templates: int = Field(100, ge=1)
    bfd_oversample: int = Field(BFD_OVERSAMPLE, ge=1, le=8)
    bfd_template_sample: Literal["independent", "targets"] = "independent"
    bfd_mirror: bool = False
    anacal_sigma: float = Field(0.8, gt=0.0, lt=3.0, description="arcsec")
    object_offset: float = Field(0.0, ge=0.0, le=100.0, description="coadd pixels")

    @model_validator(mode="before")
    @classmethod
    def _default_cell(cls, data: object) -> object:
        if not isinstance(data, dict):
            return data
        data = dict(data)
        offset = data.get("object_offset", 0.0)
        if data.get("cell_inner") is None:
            sim = data.get("sim")
            sim = SimConfig() if sim is None else SimConfig.model_validate(sim)
            data["cell_inner"] = largest_cell_inner(
                sim, data.get("coadd_pixel_scale", 0.2), data.get("cell_border", 5), offset
            )
        build = data.get("build")
        build = BuildConfig(n_noise=1) if build is None else BuildConfig.model_validate(build)
        if isinstance(offset, int | float) and offset > 0 and not build.psf_phase:
            build = build.model_copy(update={"psf_phase": True})  # psf_at off the centre
        outer = data["cell_inner"] + 2 * data.get("cell_border", 5)
        if isinstance(outer, int):  # else the field validators refuse the sizes
            # the PSF stamp left out: as large as the cell holds, up to the builder's default
            data["build"] = build.resolved(outer)
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
            raise ConfigError(f"snr must satisfy 0 < lo <= hi, got {self.snr}", value=self.snr)
        if self.cell_inner % 2 == 0:
            raise ConfigError(
                f"cell_inner must be odd so the cell centre falls on the objects, "
                f"got {self.cell_inner}",
                value=self.cell_inner,
            )
        if self.build.n_noise <= self.noise_index:
            raise ConfigError(
                f"build.n_noise = {self.build.n_noise} has no noise realization "
                f"{self.noise_index}: metacal needs one",
                value=self.noise_index,
                allowed=(0, self.build.n_noise),
            )
        if self.sim.shear[0] == 0.0 or self.sim.shear[1] != 0.0:
            raise ConfigError(
                f"the bias is measured on g1: sim.shear must be (g, 0) with g != 0, "
                f"got {self.sim.shear}",
                value=self.sim.shear,
            )
        check_method_mode(self.method, self.mode, self.reconvolution_psf)
        if self.bfd_template_sample == "targets" and self.rotated_partners:
            raise ConfigError(
                "BFD templates from the targets need rotated_partners=False: a ring partner "
                "is its twin turned by 90 degrees, a second template the prior would confuse "
                "with the target's own"
            )
        if self.object_offset > 0 and self.mode != "coadd":
            raise ConfigError(
                "object_offset places objects in the coadd's cell: coadd mode only (the "
                "epochs are measured at the objects' own positions)",
                value=self.object_offset,
            )
        if self.build.stamp_size > self.cell_inner + 2 * self.cell_border:
            raise ConfigError(
                "build.psf_size exceeds the cell outer box", value=self.build.psf_size
            )
        return self

    @property
    def bfd_snr_range(self) -> tuple[float, float] | None:
        """BFD flux-S/N selection: the paper's ``(5, 50)``, or none when the target S/N
        exceeds 50 (a high-S/N run)."""
        if self.snr is not None and self.snr[1] > 50.0:
            return None
        return (5.0, 50.0)

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


def largest_cell_inner(
    sim: SimConfig, coadd_pixel_scale: float, cell_border: int = 5, offset: float = 0.0
) -> int:
    """Largest odd cell inner size whose outer box fits every epoch stamp with Lanczos-3,
    also when moved by up to ``offset`` coadd pixels along each axis (objects at random
    positions of the cell: :attr:`ValidationSettings.object_offset`).

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
    half_outer = int(
        np.floor(reach / stretch * sim.pixel_scale / coadd_pixel_scale - offset - 1e-9)
    )
    inner = 2 * (half_outer - cell_border) + 1
    if inner < 1:
        raise ConfigError(
            f"no cell with a {cell_border}-pixel border at {coadd_pixel_scale} arcsec/pixel "
            f"fits in a {sim.stamp_size}-pixel stamp",
            value=cell_border,
        )
    return inner


def stamp_size_for_offset(
    sim: SimConfig, coadd_pixel_scale: float, cell_border: int, offset: float
) -> int:
    """The smallest epoch stamp size (pixels, >= ``sim.stamp_size``) whose largest cell,
    moved by up to ``offset`` coadd pixels, is as large as ``sim``'s unmoved one: objects
    at random positions then keep the cell (and its PSF stamp) of centred objects."""
    wanted = largest_cell_inner(sim, coadd_pixel_scale, cell_border)
    size = sim.stamp_size
    while largest_cell_inner(sim.model_copy(update={"stamp_size": size}),
                             coadd_pixel_scale, cell_border, offset) < wanted:  # fmt: skip
        size += 2
    return size


def offset_cell(settings: ValidationSettings, dx: float, dy: float) -> tuple[Cell, float, float]:
    """The one-cell sky map's cell moved so that the objects (at ``(sim.ra, sim.dec)``)
    fall ``(dx, dy)`` coadd pixels from its centre pixel, and their exact array position
    ``(x, y)`` there (the moved tangent point puts them ~1e-5 px from the aim)."""
    centred = stamp_cell(settings)
    ny, nx = centred.outer_bbox.shape
    ra, dec = (float(v) for v in centred.wcs.pixel_to_world_values(nx // 2 - dx, ny // 2 - dy))
    cell = SkyMap.from_centers([(ra, dec)], settings.skymap_config())[0].cell(0, 0)
    x, y = (float(v) for v in cell.wcs.world_to_pixel_values(settings.sim.ra, settings.sim.dec))
    return cell, x, y


def expected_inputs(settings: ValidationSettings) -> int:
    """Epochs a measurement should use: all of them, or one in single mode."""
    return 1 if settings.mode == "single" else settings.sim.n_epochs


def stamp_cell(settings: ValidationSettings) -> Cell:
    """Cell ``(0, 0)`` of the one-cell sky map centred on the objects; its centre pixel
    ``(nx // 2, ny // 2)`` of the outer box is exactly at ``(sim.ra, sim.dec)``.

    One cell serves every object, since they all share the sky position."""
    skymap = SkyMap.from_centers([(settings.sim.ra, settings.sim.dec)], settings.skymap_config())
    return skymap[0].cell(0, 0)
