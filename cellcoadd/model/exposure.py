"""Input exposures: one calibrated detector image with its WCS, noise, mask and PSF.

PSF convention
--------------
``psf`` describes the PSF *before* the pixel response, as a GalSim profile in arcsec on
the local tangent plane (``u`` West, ``v`` North; see :mod:`cellcoadd.geometry.wcs_utils`).
Drawing it with the pixel response (GalSim ``method="auto"``) through the exposure's local
WCS at a position gives the image of a point source centred there, so a star drawn the
same way into the exposure matches the PSF exactly. Three forms are accepted:

* a ``galsim.GSObject``: constant over the exposure;
* a callable ``(x, y) -> galsim.GSObject`` (0-based exposure pixels) for a varying PSF;
* a ``galsim.Image`` (an image-based PSF): an odd square stamp *already including* the
  pixel response, sampled on the exposure pixel grid and centred on its central pixel.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import galsim
import numpy as np
from astropy.wcs import WCS

from cellcoadd.geometry.box import Box
from cellcoadd.geometry.wcs_utils import canonical_wcs, local_jacobian
from cellcoadd.model.maskbits import MaskBits

PsfLike = galsim.GSObject | Callable[[float, float], galsim.GSObject] | galsim.Image


class ExposureError(ValueError):
    """An exposure is malformed (raised at construction with the visit and detector)."""


@dataclass(eq=False)
class Exposure:
    """One calibrated exposure of a detector.

    Parameters
    ----------
    image : ndarray, shape (ny, nx)
        Calibrated pixel values (counts at ``zero_point``), background subtracted.
    wcs : astropy.wcs.WCS
        Celestial WCS of ``image`` (SIP distortion allowed); pixel (0, 0) is ``image[0, 0]``.
    variance : float or ndarray
        Per-pixel variance of ``image`` (counts^2); a scalar means a uniform background.
    psf : GSObject, callable or galsim.Image
        The PSF; see the module docstring for the convention.
    visit, detector : int
        Identity of the exposure; ``(visit, detector)`` must be unique in a build.
    band : str
        Filter name.
    zero_point : float
        Magnitude zero point: a source of magnitude m has ``10**(-0.4 (m - zero_point))``
        counts.
    mask : ndarray of int, optional
        Bit mask with bits named in ``mask_bits``; default: nothing masked.
    mask_bits : MaskBits
        Names of the bits of ``mask``.
    valid_box : Box, optional
        The pixels that hold data (default the whole array).
    """

    image: np.ndarray
    wcs: WCS
    variance: float | np.ndarray
    psf: PsfLike
    visit: int
    detector: int
    band: str
    zero_point: float
    mask: np.ndarray | None = None
    mask_bits: MaskBits = field(default_factory=MaskBits)
    valid_box: Box | None = None

    def __post_init__(self) -> None:
        name = f"exposure (visit={self.visit}, detector={self.detector})"
        self.image = np.asarray(self.image)
        if self.image.ndim != 2 or self.image.size == 0:
            raise ExposureError(f"{name}: image must be a non-empty 2-D array")
        if not np.issubdtype(self.image.dtype, np.floating):
            self.image = self.image.astype(np.float64)
        if not isinstance(self.wcs, WCS) or not self.wcs.has_celestial:
            raise ExposureError(f"{name}: wcs must be a celestial astropy.wcs.WCS")
        self.wcs = canonical_wcs(self.wcs)
        if not np.isfinite(self.zero_point) or not -50.0 < self.zero_point < 100.0:
            raise ExposureError(
                f"{name}: zero_point {self.zero_point} is not a plausible magnitude"
            )
        if not isinstance(self.band, str) or not self.band:
            raise ExposureError(f"{name}: band must be a non-empty string")
        if self.mask is None:
            self.mask = np.zeros(self.image.shape, dtype=np.int32)
        self.mask = np.asarray(self.mask)
        if self.mask.shape != self.image.shape or not np.issubdtype(self.mask.dtype, np.integer):
            raise ExposureError(f"{name}: mask must be an integer array of the image's shape")
        unknown = self.mask_bits.unknown_bits(self.mask)
        if unknown:
            raise ExposureError(f"{name}: mask has bits {unknown:#x} with no name in mask_bits")
        self.mask = self.mask.astype(np.int32, copy=False)
        if np.ndim(self.variance) == 0:
            self.variance = float(self.variance)
        else:
            self.variance = np.asarray(self.variance, dtype=np.float64)
            if self.variance.shape != self.image.shape:
                raise ExposureError(f"{name}: variance array must have the image's shape")
        full = Box.from_shape(self.image.shape)
        if self.valid_box is None:
            self.valid_box = full
        elif not full.contains_box(self.valid_box):
            raise ExposureError(f"{name}: valid_box {self.valid_box} exceeds the image {full}")
        bad = ~np.isfinite(self.image) & (self.mask == 0)
        if bad.any():
            raise ExposureError(
                f"{name}: {int(bad.sum())} non-finite pixels are not flagged in the mask"
            )
        if isinstance(self.psf, galsim.Image):
            ny, nx = self.psf.array.shape
            if ny != nx or ny % 2 == 0:
                raise ExposureError(f"{name}: an image PSF must be an odd square stamp")
        elif not (isinstance(self.psf, galsim.GSObject) or callable(self.psf)):
            raise ExposureError(f"{name}: psf must be a GSObject, a callable or a galsim.Image")

    @property
    def key(self) -> tuple[int, int]:
        """``(visit, detector)``."""
        return (self.visit, self.detector)

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape  # type: ignore[return-value]

    @property
    def background_variance(self) -> float:
        """Median variance over the valid pixels (counts^2): the basis of the coadd weight."""
        if isinstance(self.variance, float):
            return self.variance
        values = self.variance[self.valid_box.slices]
        return float(np.median(values)) if values.size else float("nan")

    def local_jacobian(self, x: float, y: float) -> np.ndarray:
        """``[[du/dx, du/dy], [dv/dx, dv/dy]]`` in arcsec/pixel at exposure pixel ``(x, y)``."""
        return local_jacobian(self.wcs, x, y)

    def psf_profile(self, x: float, y: float) -> galsim.GSObject:
        """The PSF at ``(x, y)`` as a GalSim profile.

        For a profile PSF this excludes the pixel (draw with ``method="auto"``); for an
        image PSF the returned ``InterpolatedImage`` includes it (draw with
        ``method="no_pixel"``); see :attr:`psf_includes_pixel`.
        """
        if isinstance(self.psf, galsim.Image):
            jac = self.local_jacobian(x, y)
            wcs = galsim.JacobianWCS(jac[0, 0], jac[0, 1], jac[1, 0], jac[1, 1])
            image = galsim.Image(self.psf.array, wcs=wcs)
            return galsim.InterpolatedImage(image, x_interpolant="lanczos3")
        if isinstance(self.psf, galsim.GSObject):
            return self.psf
        profile = self.psf(x, y)
        if not isinstance(profile, galsim.GSObject):
            raise ExposureError(
                f"exposure (visit={self.visit}, detector={self.detector}): PSF callable "
                f"returned {type(profile).__name__}, not a galsim.GSObject"
            )
        return profile

    @property
    def psf_includes_pixel(self) -> bool:
        """Whether :meth:`psf_profile` already contains the pixel response."""
        return isinstance(self.psf, galsim.Image)
