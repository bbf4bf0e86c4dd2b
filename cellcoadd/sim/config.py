"""Configuration of the simulations of the paper's section 3 (frozen pydantic models).

Every random quantity is drawn from a generator seeded explicitly by the caller; the
configuration only holds the distributions. Defaults reproduce the paper:

* exposures at 0.27 arcsec/pixel (DES), 48 x 48 stamps, 10 epochs per object;
* Moffat PSF, beta = 3.5, FWHM log-normal with mean 0.95 arcsec and standard deviation
  0.1 arcsec, truncated to [0.8, 1.15] arcsec by redrawing; PSF shape Gaussian with means
  (0, 0.01) and standard deviation 0.01 per component;
* exponential galaxies, intrinsic ellipticity ``P(e) ~ (1 - e^2)^2 exp(-e^2 / 2 sigma_e^2)``
  with ``sigma_e = 0.02``, constant shear ``(g1, g2) = (0.02, 0)``;
* per-epoch sub-pixel shifts uniform over a pixel and per-epoch WCS Jacobian variations.

Ellipticities (PSF and galaxy) are reduced-shear-like: ``|g| = (a - b) / (a + b)``, applied
with ``GSObject.shear(g1=..., g2=...)``, in GalSim's sky frame (``u`` West, ``v`` North).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from cellcoadd.errors import ConfigError


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class PsfConfig(_Frozen):
    """Per-epoch Moffat PSF (before the pixel response).

    Parameters
    ----------
    beta : float
        Moffat index.
    fwhm_mean, fwhm_sigma : float
        Mean and standard deviation, arcsec, of the log-normal FWHM distribution (the
        moments of the log-normal itself, before truncation).
    fwhm_min, fwhm_max : float
        Truncation range, arcsec: draws outside it are redrawn.
    g1_mean, g2_mean, g_sigma : float
        Gaussian distribution of the PSF shape (reduced-shear convention).
    """

    beta: float = Field(3.5, gt=1.1)
    fwhm_mean: float = Field(0.95, gt=0.0, description="arcsec")
    fwhm_sigma: float = Field(0.1, ge=0.0, description="arcsec")
    fwhm_min: float = Field(0.8, gt=0.0, description="arcsec")
    fwhm_max: float = Field(1.15, gt=0.0, description="arcsec")
    g1_mean: float = Field(0.0, gt=-0.5, lt=0.5)
    g2_mean: float = Field(0.01, gt=-0.5, lt=0.5)
    g_sigma: float = Field(0.01, ge=0.0, lt=0.2)

    @model_validator(mode="after")
    def _check_range(self) -> PsfConfig:
        if not self.fwhm_min < self.fwhm_max:
            raise ConfigError(
                f"fwhm_min ({self.fwhm_min}) must be below fwhm_max ({self.fwhm_max})",
                value=(self.fwhm_min, self.fwhm_max),
            )
        if self.fwhm_sigma == 0 and not self.fwhm_min <= self.fwhm_mean <= self.fwhm_max:
            raise ConfigError(
                "a fixed FWHM (fwhm_sigma = 0) must lie in [fwhm_min, fwhm_max]",
                value=self.fwhm_mean,
                allowed=(self.fwhm_min, self.fwhm_max),
            )
        return self


class GalaxyConfig(_Frozen):
    """Exponential galaxies: magnitude, half-light radius and intrinsic ellipticity.

    The paper sampled flux and size from a kernel density estimate of GalSim's COSMOS
    I < 25.2 catalogue. That catalogue is a separate download, unavailable here, so the
    default is a parametric stand-in chosen to mimic it:

    * magnitude (at the simulation zero point) Gaussian, i.e. flux log-normal, with mean
      24.0 and standard deviation 0.9 mag, truncated to [20, 25.2]: most objects are faint
      and the sample stops at the COSMOS depth I = 25.2;
    * half-light radius log-normal with median 0.35 arcsec at magnitude 24, getting larger
      for brighter objects (``d log10(hlr) / d mag = -0.1``), scatter 0.45 in ln(hlr),
      truncated to [0.1, 2.0] arcsec -- the range of the HST-measured sizes of faint
      COSMOS galaxies (a median of a few tenths of an arcsec).

    These are approximate, not fitted; set ``mag_sigma = 0`` and ``hlr_ln_sigma = 0`` for a
    fixed flux and size, or pass a sampler to the simulation functions.

    Parameters
    ----------
    mag_mean, mag_sigma, mag_min, mag_max : float
        Gaussian magnitude distribution and its truncation range, mag.
    hlr_median : float
        Median half-light radius at ``mag_mean``, arcsec.
    hlr_ln_sigma : float
        Standard deviation of ln(hlr) at fixed magnitude.
    hlr_mag_slope : float
        ``d log10(hlr) / d mag`` of the median size.
    hlr_min, hlr_max : float
        Truncation range of the half-light radius, arcsec.
    sigma_e : float
        Width of the intrinsic ellipticity distribution ``P(e) ~ (1 - e^2)^2
        exp(-e^2 / 2 sigma_e^2)`` (a density in the (e1, e2) plane); 0 for round galaxies.
    """

    model: Literal["exponential"] = "exponential"
    mag_mean: float = 24.0
    mag_sigma: float = Field(0.9, ge=0.0)
    mag_min: float = 20.0
    mag_max: float = 25.2
    hlr_median: float = Field(0.35, gt=0.0, description="arcsec")
    hlr_ln_sigma: float = Field(0.45, ge=0.0)
    hlr_mag_slope: float = -0.1
    hlr_min: float = Field(0.1, gt=0.0, description="arcsec")
    hlr_max: float = Field(2.0, gt=0.0, description="arcsec")
    sigma_e: float = Field(0.02, ge=0.0, lt=1.0)

    @model_validator(mode="after")
    def _check_ranges(self) -> GalaxyConfig:
        if not self.mag_min < self.mag_max:
            raise ConfigError("mag_min must be below mag_max", value=(self.mag_min, self.mag_max))
        if not self.hlr_min < self.hlr_max:
            raise ConfigError("hlr_min must be below hlr_max", value=(self.hlr_min, self.hlr_max))
        return self


class WcsVariationConfig(_Frozen):
    """Per-epoch variation of the exposure WCS Jacobian.

    The Jacobian is ``J = s (1 + ds) R(theta) [[1 + eta1, eta2], [eta2, 1 - eta1]]`` with
    ``s`` the nominal pixel scale; ``ds``, ``eta1`` and ``eta2`` Gaussian (percent-level, as
    measured across the DES focal plane) and ``theta`` uniform in [0, 360) deg when
    ``rotate`` is set, else 0.
    """

    scale_sigma: float = Field(0.01, ge=0.0, lt=0.2)
    shear_sigma: float = Field(0.01, ge=0.0, lt=0.2)
    rotate: bool = False


class FieldConfig(_Frozen):
    """Sky region, focal plane and observing pattern of the field simulation.

    Parameters
    ----------
    n_ccd_x, n_ccd_y : int
        CCDs along x and y of the focal plane.
    ccd_nx, ccd_ny : int
        CCD size, pixels. The default, 700 (3.15 arcmin at 0.27 arcsec/pixel), is about
        four cell outer boxes across: CCD edges and gaps cross some cells, which lose
        those visits (edge-free selection), but most cells keep most visits. Much smaller
        CCDs leave cells empty.
    ccd_gap : int
        Gap between neighbouring CCDs, pixels.
    edge_pixels : int
        Pixels along each CCD edge flagged EDGE and left out of the valid box.
    dither : "random", "spiral" or "none"
        Pointing pattern: uniform in a disk, a Vogel (sunflower) spiral filling the disk,
        or no offsets.
    dither_radius : float
        Radius of the dither disk, arcsec.
    rotate : bool
        Rotate the focal plane by a random angle per visit.
    sip_k : float
        Radial distortion coefficient, 1/pixel^2 (``x' = x (1 + k r^2)`` about the
        boresight, written as SIP); 0 for a pure TAN WCS.
    psf_fwhm_edge : float
        Fractional FWHM increase at the focal-plane corner (0: a constant PSF per visit).
    psf_g_edge : float
        PSF shear at the focal-plane corner in a radial pattern (0: none).
    galaxy_density, star_density : float
        Objects per square arcmin.
    star_mag_min, star_mag_max : float
        Stars are uniform in magnitude over this range.
    region_margin : float
        Objects are placed over the patch outer box grown by this margin, arcsec.
    noise_scatter : float
        Fractional standard deviation of the per-visit noise level.
    zero_point_scatter : float
        Standard deviation of the per-visit zero point, mag.
    bad_columns, cosmic_rays : float
        Mean number of bad columns and cosmic rays per CCD (Poisson).
    """

    n_ccd_x: int = Field(3, ge=1, le=16)
    n_ccd_y: int = Field(3, ge=1, le=16)
    ccd_nx: int = Field(700, ge=32)
    ccd_ny: int = Field(700, ge=32)
    ccd_gap: int = Field(20, ge=0)
    edge_pixels: int = Field(2, ge=0)
    dither: Literal["random", "spiral", "none"] = "random"
    dither_radius: float = Field(40.0, ge=0.0, description="arcsec")
    rotate: bool = False
    sip_k: float = Field(0.0, description="1/pixel^2")
    psf_fwhm_edge: float = Field(0.0, ge=0.0, lt=1.0)
    psf_g_edge: float = Field(0.0, ge=0.0, lt=0.3)
    galaxy_density: float = Field(20.0, ge=0.0, description="per arcmin^2")
    star_density: float = Field(2.0, ge=0.0, description="per arcmin^2")
    star_mag_min: float = 18.0
    star_mag_max: float = 24.0
    region_margin: float = Field(10.0, ge=0.0, description="arcsec")
    noise_scatter: float = Field(0.1, ge=0.0, lt=0.5)
    zero_point_scatter: float = Field(0.05, ge=0.0, lt=1.0)
    bad_columns: float = Field(0.5, ge=0.0)
    cosmic_rays: float = Field(3.0, ge=0.0)

    @model_validator(mode="after")
    def _check(self) -> FieldConfig:
        if 2 * self.edge_pixels >= min(self.ccd_nx, self.ccd_ny):
            raise ConfigError("edge_pixels leaves no valid pixels on a CCD", value=self.edge_pixels)
        if not self.star_mag_min <= self.star_mag_max:
            raise ConfigError(
                "star_mag_min must not exceed star_mag_max",
                value=(self.star_mag_min, self.star_mag_max),
            )
        return self


class SimConfig(_Frozen):
    """All the settings of a simulation (frozen; defaults from the paper's section 3).

    Parameters
    ----------
    pixel_scale : float
        Nominal exposure pixel scale, arcsec/pixel.
    stamp_size : int
        Side of the square stamps of the stamp mode, pixels.
    n_epochs : int
        Epochs per object in the stamp mode.
    max_shift : float
        Per-epoch sub-pixel shifts are uniform in ``[-max_shift, max_shift)`` pixels per axis.
    noise_sigma : float
        Gaussian pixel noise, counts at ``zero_point``. The default, 9.5, gives a point
        source of i = 23.0 an optimal S/N of 10 in one epoch with the mean PSF, roughly
        the single-epoch depth of DES i-band images.
    zero_point : float
        Magnitude zero point of the simulated images.
    band : str
        Filter name written into the exposures.
    shear : tuple of float
        Constant reduced shear ``(g1, g2)`` applied to every galaxy.
    ra, dec : float
        Sky position of the stamp-mode objects, deg (all objects share it, so one sky map
        centred there serves them all).
    """

    pixel_scale: float = Field(0.27, gt=0.0, le=5.0, description="arcsec/pixel")
    stamp_size: int = Field(48, ge=8, le=1024)
    n_epochs: int = Field(10, ge=1, le=1000)
    max_shift: float = Field(0.5, ge=0.0, le=0.5, description="pixels")
    noise_sigma: float = Field(9.5, ge=0.0, description="counts")
    zero_point: float = Field(30.0, gt=-50.0, lt=100.0, description="mag")
    band: str = Field("i", min_length=1)
    shear: tuple[float, float] = (0.02, 0.0)
    ra: float = Field(60.0, ge=0.0, lt=360.0, description="deg")
    dec: float = Field(-30.0, gt=-89.0, lt=89.0, description="deg")
    psf: PsfConfig = PsfConfig()
    galaxy: GalaxyConfig = GalaxyConfig()
    wcs: WcsVariationConfig = WcsVariationConfig()
    field: FieldConfig = FieldConfig()

    @model_validator(mode="after")
    def _check_shear(self) -> SimConfig:
        if self.shear[0] ** 2 + self.shear[1] ** 2 >= 1.0:
            raise ConfigError(f"|shear| must be below 1, got {self.shear}", value=self.shear)
        return self
