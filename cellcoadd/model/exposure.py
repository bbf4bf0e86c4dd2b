"""Input exposures: one calibrated detector image with its WCS, noise, mask and PSF.

PSF convention
--------------
``psf`` is a :class:`~cellcoadd.model.psf.PsfModel` (``GalSimPsf``, ``ImagePsf``,
``CallablePsf``, ``PsfexPsf``, ``PiffPsf``) that draws the image of a point source,
pixel response included, at any exposure position; see :mod:`cellcoadd.model.psf`. For
convenience bare forms are accepted and wrapped (:attr:`Exposure.psf_model`):

* a ``galsim.GSObject``: constant over the exposure, *before* the pixel response, in
  arcsec on the local tangent plane (``u`` West, ``v`` North);
* a :class:`~cellcoadd.model.psf_profiles.VaryingPsf` or
  :class:`~cellcoadd.model.psf_profiles.GridPsf` (callables ``(x, y) -> galsim.GSObject``
  of 0-based exposure pixels), also *before* the pixel. Any other callable must say
  whether its profiles include the pixel: ``GalSimPsf(func)`` (without) or
  ``CallablePsf(func, includes_pixel=True)`` (PSFEx's, Piff's); a bare one is refused;
* a ``galsim.Image``: an odd square stamp *already including* the pixel response,
  sampled on the exposure pixel grid and centred on its central pixel.

Profiles and stamps must have unit flux (:data:`~cellcoadd.model.psf.PSF_FLUX_TOLERANCE`).
"""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Callable
from dataclasses import InitVar, dataclass, field
from functools import cached_property
from typing import TypeAlias

import galsim
import numpy as np
from astropy.wcs import WCS

from cellcoadd.errors import ExposureError, PsfError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.exact_wcs import ExactWCS
from cellcoadd.geometry.wcs_utils import canonical_wcs, local_jacobian
from cellcoadd.model.inputs import check_band_name
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.psf import PsfModel, as_psf_model

PsfLike: TypeAlias = (
    PsfModel | galsim.GSObject | Callable[[float, float], galsim.GSObject] | galsim.Image
)


@dataclass(eq=False, frozen=True)
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
    psf : PsfModel, GSObject, callable or galsim.Image
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
    origin : (int, int)
        Detector pixel ``(x, y)`` of ``image[0, 0]``: non-zero when the exposure is a
        cutout of a detector image (``wcs`` then describes the cutout). The PSF model and
        the noise realizations are evaluated in detector pixels, so a cutout gives the
        same values as the whole detector image.
    wcs_is_canonical : bool
        Declare ``wcs`` already in :func:`~cellcoadd.geometry.wcs_utils.canonical_wcs`
        form (e.g. from :func:`~cellcoadd.geometry.wcs_utils.shifted_wcs` of a canonical
        WCS), which skips putting it in that form again (~0.2 ms). Readers set it; it is
        ignored for a WCS that is not an :class:`~cellcoadd.geometry.exact_wcs.ExactWCS`
        (which would not pickle exactly).

    Notes
    -----
    Frozen: fields are validated once, at construction; use :meth:`replace` for a
    modified copy (validated again, but a WCS it keeps is not put in canonical form a
    second time, which ``dataclasses.replace`` would do).
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
    origin: tuple[int, int] = (0, 0)
    wcs_is_canonical: InitVar[bool] = False

    def __post_init__(self, wcs_is_canonical: bool) -> None:
        name = f"exposure (visit={self.visit}, detector={self.detector})"
        for field_name in ("visit", "detector"):
            value = getattr(self, field_name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise ExposureError(f"{name}: {field_name} must be an integer, got {value!r}")
            object.__setattr__(self, field_name, int(value))
        try:
            # surrounding spaces survive exposure files but not coadd input tables,
            # where build_patch refuses them
            check_band_name(self.band.strip(" ") if isinstance(self.band, str) else "")
        except ValueError as err:
            raise ExposureError(f"{name}: {err} (band={self.band!r})") from None
        object.__setattr__(self, "image", np.asarray(self.image))
        if self.image.ndim != 2 or self.image.size == 0:
            raise ExposureError(f"{name}: image must be a non-empty 2-D array")
        if self.image.dtype.kind not in "biuf":
            raise ExposureError(f"{name}: image must be real-valued, got dtype {self.image.dtype}")
        if not np.issubdtype(self.image.dtype, np.floating):
            object.__setattr__(self, "image", self.image.astype(np.float64))
        object.__setattr__(
            self, "wcs", _checked_wcs(name, self.wcs, self.image.shape, wcs_is_canonical)
        )
        zero_point = self.zero_point
        if isinstance(zero_point, bool) or not isinstance(zero_point, numbers.Real):
            raise ExposureError(f"{name}: zero_point must be a number, got {zero_point!r}")
        if not np.isfinite(zero_point) or not -50.0 < zero_point < 100.0:
            raise ExposureError(f"{name}: zero_point {zero_point} is not a plausible magnitude")
        object.__setattr__(self, "zero_point", float(zero_point))
        if self.mask is None:
            object.__setattr__(self, "mask", np.zeros(self.image.shape, dtype=np.int32))
        object.__setattr__(self, "mask", np.asarray(self.mask))
        if self.mask.shape != self.image.shape or not np.issubdtype(self.mask.dtype, np.integer):
            raise ExposureError(f"{name}: mask must be an integer array of the image's shape")
        unknown = self.mask_bits.unknown_bits(self.mask)
        if unknown:
            raise ExposureError(f"{name}: mask has bits {unknown:#x} with no name in mask_bits")
        object.__setattr__(self, "mask", self.mask.astype(np.int32, copy=False))
        object.__setattr__(
            self, "variance", _checked_variance(name, self.variance, self.image.shape)
        )
        full = Box.from_shape(self.image.shape)
        if self.valid_box is None:
            object.__setattr__(self, "valid_box", full)
        elif not isinstance(self.valid_box, Box):
            raise ExposureError(f"{name}: valid_box must be a Box, got {self.valid_box!r}")
        elif not full.contains_box(self.valid_box):
            raise ExposureError(f"{name}: valid_box {self.valid_box} exceeds the image {full}")
        bad = ~np.isfinite(self.image) & (self.mask == 0)
        if bad.any():
            raise ExposureError(
                f"{name}: {int(bad.sum())} non-finite pixels are not flagged in the mask"
            )
        if not (
            isinstance(self.origin, tuple)
            and len(self.origin) == 2
            and all(isinstance(v, numbers.Integral) and v >= 0 for v in self.origin)
        ):
            raise ExposureError(f"{name}: origin must be two non-negative integers")
        object.__setattr__(self, "origin", (int(self.origin[0]), int(self.origin[1])))
        try:
            model = as_psf_model(self.psf)
        except PsfError as err:
            raise ExposureError(f"{name}: {err}") from None
        object.__setattr__(self, "_psf_model", model)

    def replace(self, **changes: object) -> Exposure:
        """A copy with ``changes`` (field names as keywords), validated like a new exposure.

        When ``wcs`` is not changed the copy shares this exposure's WCS object, already in
        canonical form: converting it again (~0.2 ms,
        :func:`~cellcoadd.geometry.wcs_utils.canonical_wcs`) would give the same values.
        A new ``wcs`` is converted unless ``wcs_is_canonical=True`` is passed with it.
        """
        if "wcs" not in changes:
            changes["wcs_is_canonical"] = True
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]  # field names

    @property
    def key(self) -> tuple[int, int]:
        """``(visit, detector)``."""
        return (self.visit, self.detector)

    @property
    def shape(self) -> tuple[int, int]:
        ny, nx = self.image.shape
        return (ny, nx)

    @cached_property
    def background_variance(self) -> float:
        """Median variance over the valid pixels (counts^2): the basis of the coadd weight.

        Non-finite values (usually at masked pixels) are left out; NaN if none is left.
        """
        if isinstance(self.variance, float):
            return self.variance
        assert self.valid_box is not None  # set at construction
        values = self.variance[self.valid_box.slices]
        values = values[np.isfinite(values)]
        return float(np.median(values)) if values.size else float("nan")

    def local_jacobian(self, x: float, y: float) -> np.ndarray:
        """``[[du/dx, du/dy], [dv/dx, dv/dy]]`` in arcsec/pixel at exposure pixel ``(x, y)``."""
        return local_jacobian(self.wcs, x, y)

    @property
    def psf_model(self) -> PsfModel:
        """The PSF as a :class:`~cellcoadd.model.psf.PsfModel` (``psf`` itself, or its
        wrapper for the bare forms)."""
        model: PsfModel = self.__dict__["_psf_model"]  # set at construction
        return model

    def draw_psf(
        self, x: float, y: float, box: Box, center: tuple[float, float] | None = None
    ) -> np.ndarray:
        """The PSF at exposure pixel ``(x, y)``, pixel included, unit flux, over ``box``,
        centred at ``(x, y)`` or ``center`` (see :meth:`cellcoadd.model.psf.PsfModel.draw`).

        Positions and ``box`` are in this exposure's pixels; the model is asked in
        detector pixels (shifted by :attr:`origin`)."""
        jacobian = self.local_jacobian(x, y)
        ox, oy = self.origin
        if ox == 0 and oy == 0:
            return self.psf_model.draw(x, y, box, jacobian, center)
        shifted = box.shifted(ox, oy)
        if center is not None:
            center = (center[0] + ox, center[1] + oy)
        return self.psf_model.draw(x + ox, y + oy, shifted, jacobian, center)


def _checked_wcs(name: str, wcs: object, shape: tuple[int, ...], is_canonical: bool = False) -> WCS:
    """``wcs`` in canonical form (as it is when ``is_canonical``), if it is a usable
    equatorial celestial WCS of the image.

    Refused: non-celestial WCSs, other frames (galactic, ecliptic: their longitudes would
    be taken for RA), more than two pixel axes, and a singular or non-finite pixel scale
    at the image centre.
    """
    if not isinstance(wcs, WCS):
        raise ExposureError(f"{name}: wcs must be a celestial astropy.wcs.WCS")
    checked: WCS = wcs
    try:
        celestial, n_axes = checked.has_celestial, checked.pixel_n_dim
        if celestial and n_axes == 2:
            if not (is_canonical and isinstance(checked, ExactWCS)):
                checked = canonical_wcs(checked)
            axes = (checked.wcs.lngtyp, checked.wcs.lattyp)
            ny, nx = shape
            jacobian = local_jacobian(checked, (nx - 1) / 2.0, (ny - 1) / 2.0)
    except Exception as err:  # astropy raises several types for broken WCSs
        raise ExposureError(f"{name}: the WCS cannot be evaluated ({_one_line(err)})") from None
    if not celestial:
        raise ExposureError(f"{name}: wcs must be a celestial astropy.wcs.WCS")
    if n_axes != 2:
        raise ExposureError(
            f"{name}: wcs must have 2 pixel axes, got {n_axes} (pass wcs.celestial)"
        )
    if axes != ("RA", "DEC"):
        raise ExposureError(f"{name}: wcs must be in RA/Dec, got {axes[0]}/{axes[1]} axes")
    area = abs(float(np.linalg.det(jacobian))) if np.all(np.isfinite(jacobian)) else 0.0
    if not area > 0.0:
        raise ExposureError(f"{name}: the WCS is singular or not finite at the image centre")
    return checked


def _one_line(err: Exception) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return "; ".join(lines) or type(err).__name__


def _checked_variance(name: str, variance: object, shape: tuple[int, ...]) -> float | np.ndarray:
    """A scalar (float) or an image-shaped float64 array; zero, negative or non-finite
    values are allowed here and lead to per-cell rejections (``bad_weight``)."""
    if np.ndim(variance) == 0:  # type: ignore[arg-type]  # any object: checked here
        try:
            return float(variance)  # type: ignore[arg-type]  # a 0-d array or number
        except (TypeError, ValueError):
            raise ExposureError(f"{name}: variance must be a number or an array") from None
    array = np.asarray(variance)
    if array.dtype.kind not in "biuf":
        raise ExposureError(f"{name}: variance must be real-valued, got dtype {array.dtype}")
    if array.shape != shape:
        raise ExposureError(f"{name}: variance array must have the image's shape")
    return array.astype(np.float64, copy=False)
