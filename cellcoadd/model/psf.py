"""PSF models that draw themselves: the one question the builder asks of an exposure's PSF.

Contract
--------
``model.draw(x, y, box, jacobian)`` returns the PSF at exposure pixel ``(x, y)`` as the
image of a **unit-flux point source centred there** (0-based, pixel centres at
integers; ``center=`` places it elsewhere, the model still evaluated at ``(x, y)``),
**pixel response included**, sampled on the exposure pixels of ``box`` (half-open; array
``[0, 0]`` is pixel ``(box.x_start, box.y_start)``). ``jacobian`` is the exposure WCS's
local Jacobian at ``(x, y)``, ``[[du/dx, du/dy], [dv/dx, dv/dy]]`` in arcsec/pixel (``u``
West, ``v`` North): models defined on the sky use it, models defined on the detector's
pixels ignore it. A star drawn into the exposure by the same model is, by construction,
what the coadd PSF describes.

``model.includes_pixel`` says whether the model's *native* form already contains the
pixel response (then it is drawn without adding it again), for the record and the docs;
the builder never branches on it.

=================  =============================================  ============  =========
model              what it holds                                  native form   pixel
=================  =============================================  ============  =========
``GalSimPsf``      a GSObject, or a callable (x, y) -> GSObject   sky, arcsec   added
``ImagePsf``       an odd square stamp on the exposure pixels     detector px   included
``CallablePsf``    a callable (x, y) -> GSObject with a flag      sky, arcsec   flag
``PsfexPsf``       a parsed PSFEx model (:class:`PsfexData`)      detector px   included
``PiffPsf``        a loaded Piff model (``cellcoadd[piff]``)      Piff's WCS    included
=================  =============================================  ============  =========

The model classes never read files (``model`` knows nothing of files): PSFEx and Piff
files are read, recognised by content and parsed whole by :mod:`cellcoadd.io`
(``cellcoadd.io.read_psfex(path)``, ``read_piff(path, trusted=True)``,
``read_psf_file(path)``); ``PsfexPsf(path)`` says so.

:func:`as_psf_model` turns the forms an :class:`~cellcoadd.model.exposure.Exposure`
accepts into one of these: a bare GSObject (or ``VaryingPsf``, ``GridPsf``) is a
``GalSimPsf``, a ``galsim.Image`` an ``ImagePsf``; a bare callable is refused (it must
state whether it includes the pixel).

Every model is checked where it is made or evaluated: profiles and stamps must have
unit flux within :data:`PSF_FLUX_TOLERANCE` (:func:`check_psf_flux`) and finite values;
PSFEx content is checked by :class:`PsfexData`.
"""

from __future__ import annotations

import hashlib
import math
import os
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import galsim
import numpy as np

from cellcoadd.errors import PsfError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.wcs_utils import jacobian_wcs
from cellcoadd.model.psf_profiles import MAX_STAMP_SIZE, GridPsf, VaryingPsf


def _stamp(box: Box, wcs: galsim.BaseWCS) -> galsim.ImageD:
    """A zeroed GalSim image over ``box`` (0-based exposure pixels) with ``wcs``."""
    bounds = galsim.BoundsI(box.x_start, box.x_stop - 1, box.y_start, box.y_stop - 1)
    return galsim.ImageD(bounds, wcs=wcs)


#: Largest accepted ``|flux - 1|`` of a PSF profile or stamp: a PSF is the image of a
#: unit-flux point source; a model of another flux would change the coadd PSF's shape
#: (its inputs are weighted as if it had unit flux). PSFEx stamps sum to 1 within ~0.5%.
PSF_FLUX_TOLERANCE = 0.01


def check_psf_flux(flux: float, where: str) -> None:
    """Refuse a PSF whose total flux is not 1 within :data:`PSF_FLUX_TOLERANCE`.

    Raises
    ------
    PsfError
        Naming ``where`` and the flux.
    """
    if not (math.isfinite(flux) and abs(flux - 1.0) <= PSF_FLUX_TOLERANCE):
        raise PsfError(
            f"{where}: the PSF has flux {flux:.6g}, not 1 within {PSF_FLUX_TOLERANCE} (a PSF "
            "is the image of a unit-flux point source: normalise it, e.g. "
            "profile.withFlux(1.0) or stamp / stamp.sum())"
        )


def _user_profile(func: Callable[[float, float], Any], x: float, y: float) -> galsim.GSObject:
    """``func(x, y)``, which must be a unit-flux GSObject; any failure of user code is a
    PsfError."""
    try:
        profile = func(x, y)
    except Exception as err:  # user code may fail in any way: the input is rejected
        raise PsfError(f"the PSF callable failed at ({x:.2f}, {y:.2f}): {err!r}") from err
    if not isinstance(profile, galsim.GSObject):
        raise PsfError(f"the PSF callable returned {type(profile).__name__}, not a GSObject")
    check_psf_flux(profile.flux, f"the PSF callable at ({x:.2f}, {y:.2f})")
    return profile


Center = tuple[float, float] | None


def _draw_profile(
    profile: galsim.GSObject,
    image: galsim.Image,
    x: float,
    y: float,
    center: Center,
    method: str,
) -> np.ndarray:
    """Draw ``profile`` (the PSF at ``(x, y)``) into ``image``, centred at ``center`` or
    ``(x, y)``."""
    cx, cy = center if center is not None else (x, y)
    try:
        profile.drawImage(image=image, center=galsim.PositionD(cx, cy), method=method)
    except (galsim.GalSimError, ValueError, MemoryError) as err:
        raise PsfError(f"the PSF could not be drawn at ({x:.2f}, {y:.2f}): {err}") from err
    return image.array


class PsfModel(ABC):
    """An exposure's PSF: see the module docstring for the contract."""

    #: whether the native form of the model already contains the pixel response
    includes_pixel: bool
    #: whether the model is the same at every position (then the builder draws one
    #: oversampled core per exposure region instead of interpolating between several)
    constant: bool = False

    @abstractmethod
    def draw(
        self, x: float, y: float, box: Box, jacobian: np.ndarray, center: Center = None
    ) -> np.ndarray:
        """Unit-flux point source at exposure pixel ``(x, y)``, pixel included, over ``box``.

        Parameters
        ----------
        x, y : float
            Centre, 0-based exposure pixels.
        box : Box
            Exposure pixels to sample (half-open).
        jacobian : ndarray, shape (2, 2)
            Local WCS Jacobian at ``(x, y)``, arcsec/pixel.
        center : (float, float), optional
            Where to centre the point source, exposure pixels (default ``(x, y)``).

        Returns
        -------
        ndarray of float64, shape ``box.shape``

        Raises
        ------
        PsfError
            When the model cannot be evaluated there.
        """

    def pixel_profile(self, x: float, y: float, jacobian: np.ndarray) -> galsim.GSObject:
        """The effective PSF (pixel included, unit flux) at exposure pixel ``(x, y)`` as a
        profile in exposure pixels (``x``, ``y`` axes, unit pixel scale).

        Raises
        ------
        PsfError
            When the model cannot be evaluated there, or (a model without a profile
            form) never: :meth:`draw_core` then samples :meth:`draw` at each phase.
        """
        raise PsfError(f"{type(self).__name__} has no profile form")

    def draw_core(
        self, x: float, y: float, jacobian: np.ndarray, half: int, oversampling: int
    ) -> np.ndarray:
        """The effective PSF at exposure pixel ``(x, y)`` sampled ``oversampling`` times per
        exposure pixel over ``[-half, half]`` pixels around the source.

        Returns
        -------
        ndarray of float64, shape ``(m, m)``, ``m = 2 half oversampling + 1``
            ``[j, i]`` the PSF at offset ``((i - c) / oversampling, (j - c) /
            oversampling)`` exposure pixels, ``c = (m - 1) / 2``, per unit exposure-pixel
            area: the values at whole-pixel offsets are the pixels of a star drawn there.
            For :mod:`cellcoadd.model.psf_phase`.

        Raises
        ------
        PsfError
            When the model cannot be evaluated there.
        """
        side = 2 * half * oversampling + 1
        try:
            profile = self.pixel_profile(x, y, jacobian)
        except PsfError:
            profile = None
        if profile is not None:
            image = galsim.ImageD(side, side, scale=1.0 / oversampling)
            try:
                profile.drawImage(image=image, method="no_pixel")
            except (galsim.GalSimError, ValueError, MemoryError) as err:
                raise PsfError(f"the PSF could not be drawn at ({x:.2f}, {y:.2f}): {err}") from err
            return image.array * float(oversampling**2)
        # no profile: one draw per phase, interleaved
        out = np.empty((side, side))
        ix, iy = math.floor(x), math.floor(y)
        box = Box(x_start=ix - half, x_stop=ix + half + 2, y_start=iy - half, y_stop=iy + half + 2)
        for a in range(oversampling):
            for b in range(oversampling):
                # the source at (ix + 1 - a/N, iy + 1 - b/N): the stamp's column 1 + m is
                # at offset m - half + a/N, the sample a + N m
                cx, cy = ix + 1 - a / oversampling, iy + 1 - b / oversampling
                stamp = self.draw(x, y, box, jacobian, center=(cx, cy))
                n_x, n_y = len(range(a, side, oversampling)), len(range(b, side, oversampling))
                out[b::oversampling, a::oversampling] = stamp[1 : 1 + n_y, 1 : 1 + n_x]
        return out


class GalSimPsf(PsfModel):
    """A GalSim profile *before* the pixel, constant or a callable of position.

    Parameters
    ----------
    profile : galsim.GSObject or callable
        A GSObject in arcsec on the local tangent plane, or ``(x, y) -> GSObject`` of
        0-based exposure pixels. Drawn with GalSim's ``method="auto"``, which convolves
        with the pixel.
    """

    includes_pixel = False

    def __init__(self, profile: galsim.GSObject | Callable[[float, float], galsim.GSObject]):
        if not (isinstance(profile, galsim.GSObject) or callable(profile)):
            raise PsfError(f"GalSimPsf needs a GSObject or a callable, got {profile!r}")
        if isinstance(profile, galsim.GSObject):
            check_psf_flux(profile.flux, "GalSimPsf")
        self.profile = profile
        self.constant = isinstance(profile, galsim.GSObject)

    def at(self, x: float, y: float) -> galsim.GSObject:
        """The pre-pixel profile at exposure pixel ``(x, y)``."""
        if isinstance(self.profile, galsim.GSObject):
            return self.profile
        return _user_profile(self.profile, x, y)

    def draw(
        self, x: float, y: float, box: Box, jacobian: np.ndarray, center: Center = None
    ) -> np.ndarray:
        image = _stamp(box, jacobian_wcs(jacobian))
        return _draw_profile(self.at(x, y), image, x, y, center, "auto")

    def pixel_profile(self, x: float, y: float, jacobian: np.ndarray) -> galsim.GSObject:
        return _with_pixel(jacobian_wcs(jacobian).toImage(self.at(x, y)))


class CallablePsf(PsfModel):
    """A callable ``(x, y) -> GSObject`` (arcsec, sky) whose pixel content is stated.

    Parameters
    ----------
    func : callable
        0-based exposure pixel -> GalSim profile in arcsec on the local tangent plane, e.g.
        ``lambda x, y: psfex.getPSF(galsim.PositionD(x + 1, y + 1))`` for a
        ``galsim.des.DES_PSFEx`` read with a WCS (mind its 1-based positions).
    includes_pixel : bool
        Required: whether the profile already contains the pixel response (PSFEx and
        Piff profiles do; a Moffat of the atmosphere does not).
    """

    def __init__(self, func: Callable[[float, float], galsim.GSObject], *, includes_pixel: bool):
        if not callable(func):
            raise PsfError(f"CallablePsf needs a callable, got {func!r}")
        if not isinstance(includes_pixel, bool):
            raise PsfError("CallablePsf needs includes_pixel=True or False")
        self.func = func
        self.includes_pixel = includes_pixel

    def draw(
        self, x: float, y: float, box: Box, jacobian: np.ndarray, center: Center = None
    ) -> np.ndarray:
        method = "no_pixel" if self.includes_pixel else "auto"
        image = _stamp(box, jacobian_wcs(jacobian))
        return _draw_profile(_user_profile(self.func, x, y), image, x, y, center, method)

    def pixel_profile(self, x: float, y: float, jacobian: np.ndarray) -> galsim.GSObject:
        profile = jacobian_wcs(jacobian).toImage(_user_profile(self.func, x, y))
        return profile if self.includes_pixel else _with_pixel(profile)


class ImagePsf(PsfModel):
    """A constant PSF given as a stamp that includes the pixel response.

    Parameters
    ----------
    image : galsim.Image or ndarray
        Odd square stamp sampled on the exposure's pixel grid, centred on its central
        pixel; interpolated with Lanczos-3 to the requested sub-pixel centre.
    """

    includes_pixel = True
    constant = True

    def __init__(self, image: galsim.Image | np.ndarray):
        array = np.asarray(image.array if isinstance(image, galsim.Image) else image)
        ny, nx = array.shape if array.ndim == 2 else (0, 0)
        if ny != nx or ny % 2 == 0:
            raise PsfError(f"an image PSF must be an odd square stamp, got shape {array.shape}")
        if not (np.all(np.isfinite(array)) and array.sum() > 0):
            raise PsfError("an image PSF must be finite with a positive sum")
        check_psf_flux(float(array.sum()), "ImagePsf (the sum of the stamp)")
        self.image = image if isinstance(image, galsim.Image) else galsim.Image(array)

    def draw(
        self, x: float, y: float, box: Box, jacobian: np.ndarray, center: Center = None
    ) -> np.ndarray:
        wcs = jacobian_wcs(jacobian)
        stamp = galsim.Image(self.image.array, wcs=wcs)
        profile = galsim.InterpolatedImage(stamp, x_interpolant="lanczos3")
        return _draw_profile(profile, _stamp(box, wcs), x, y, center, "no_pixel")

    def pixel_profile(self, x: float, y: float, jacobian: np.ndarray) -> galsim.GSObject:
        # the stamp is on the exposure's pixels: a unit pixel scale
        return galsim.InterpolatedImage(
            galsim.Image(self.image.array, scale=1.0), x_interpolant="lanczos3"
        )


def _refuse_path(cls: type, first: object) -> None:
    """Model classes never read files (``model`` knows nothing of files): say what does."""
    if isinstance(first, (str, os.PathLike)):
        reader = "read_psfex(path)" if cls is PsfexPsf else "read_piff(path, trusted=True)"
        raise PsfError(
            f"{cls.__name__} is made from a parsed model file: read {os.fspath(first)!r} with "
            f"cellcoadd.io.{reader} (or cellcoadd.io.read_psf_file)"
        )


class _FileModel(PsfModel):
    """A PSF model parsed from a model file; keeps the file's bytes (to store it in an
    exposure file, and to compare models by content) and the name it was read from."""

    includes_pixel = True

    def __init__(self, data: bytes | None, source: str) -> None:
        if not isinstance(data, bytes) or not data:
            raise PsfError(f"{type(self).__name__} needs the model file's bytes")
        self.data = data
        self.source = source
        self.sha256 = hashlib.sha256(data).hexdigest()

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, _FileModel)
            and type(other) is type(self)
            and other.sha256 == self.sha256
        )

    def __hash__(self) -> int:
        return hash((type(self).__name__, self.sha256))


@dataclass(frozen=True, eq=False)
class PsfexData:
    """The content of a PSFEx model file, as parsed (see :func:`cellcoadd.io.read_psfex`).

    The effective PSF (pixel included) at 1-based image position ``(X, Y)`` is
    ``sum_k P_k basis[k]`` with ``P_k`` the monomials ``xs**i * ys**j`` (``j`` outer,
    ``i + j <= degree``) of ``xs = (X - zero[0]) / scale[0]``, ``ys = (Y - zero[1]) /
    scale[1]``, sampled every ``sample`` image pixels.

    Parameters
    ----------
    basis : ndarray, shape (n_terms, ny, nx)
        ``PSF_MASK``: one stamp per polynomial term, ``n_terms = (degree+1)(degree+2)/2``;
        odd sides, finite values.
    degree : int
        ``POLDEG1`` (0..8).
    zero : (float, float)
        ``POLZERO1``, ``POLZERO2``, 1-based image pixels.
    scale : (float, float)
        ``POLSCAL1``, ``POLSCAL2``, image pixels, finite and non-zero.
    sample : float
        ``PSF_SAMP``: image pixels per PSFEx sample, finite, in (0, 100].

    Raises
    ------
    PsfError
        When any of the above does not hold.
    """

    basis: np.ndarray
    degree: int
    zero: tuple[float, float]
    scale: tuple[float, float]
    sample: float

    def __post_init__(self) -> None:
        basis = np.asarray(self.basis)
        if isinstance(self.degree, bool) or not isinstance(self.degree, (int, np.integer)):
            raise PsfError(f"PSFEx POLDEG1 must be an integer, got {self.degree!r}")
        if not 0 <= int(self.degree) <= MAX_PSFEX_DEGREE:
            raise PsfError(f"PSFEx POLDEG1 = {self.degree} is outside 0..{MAX_PSFEX_DEGREE}")
        n_terms = (self.degree + 1) * (self.degree + 2) // 2
        if basis.ndim != 3 or basis.shape[0] != n_terms:
            raise PsfError(
                f"PSFEx PSF_MASK has shape {basis.shape}, expected ({n_terms}, ny, nx) for "
                f"POLDEG1 = {self.degree}"
            )
        if not all(n % 2 == 1 and n <= MAX_STAMP_SIZE for n in basis.shape[1:]):
            raise PsfError(f"PSFEx stamps must have odd sides <= {MAX_STAMP_SIZE}: {basis.shape}")
        if not np.issubdtype(basis.dtype, np.floating) or not np.all(np.isfinite(basis)):
            raise PsfError("PSFEx PSF_MASK must hold finite floating-point values")
        values = (*self.zero, *self.scale, self.sample)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            raise PsfError(f"PSFEx POLZERO, POLSCAL and PSF_SAMP must be finite, got {values}")
        if self.scale[0] == 0 or self.scale[1] == 0:
            raise PsfError(f"PSFEx POLSCAL1, POLSCAL2 = {self.scale} must be non-zero")
        if not 0 < self.sample <= 100:
            raise PsfError(f"PSFEx PSF_SAMP = {self.sample} must be in (0, 100] pixels")
        if not basis[0].sum() > 0:
            raise PsfError("PSFEx constant term of PSF_MASK does not have a positive sum")
        basis.setflags(write=False)
        object.__setattr__(self, "basis", basis)
        object.__setattr__(self, "degree", int(self.degree))

    def stamp(self, x1: float, y1: float) -> np.ndarray:
        """The sampled PSF at 1-based image position ``(x1, y1)`` (float32, as GalSim's
        ``DES_PSFEx.getPSFArray``)."""
        xs = (x1 - self.zero[0]) / self.scale[0]
        ys = (y1 - self.zero[1]) / self.scale[1]
        terms = np.array(
            [xs**i * ys**j for j in range(self.degree + 1) for i in range(self.degree + 1 - j)]
        )
        return np.tensordot(terms, self.basis, (0, 0)).astype(np.float32)


#: Largest PSFEx polynomial degree accepted (PSFEx itself uses up to 3 or 4).
MAX_PSFEX_DEGREE = 8


class PsfexPsf(_FileModel):
    """A PSFEx model, parsed from a ``.psf`` file by :func:`cellcoadd.io.read_psfex`.

    PSFEx samples the effective PSF (pixel included) every ``PSF_SAMP`` pixels, with
    polynomials in SExtractor's 1-based ``X_IMAGE``/``Y_IMAGE``: the model is evaluated
    at ``(x + 1, y + 1)`` for 0-based ``(x, y)`` as GalSim's ``galsim.des.DES_PSFEx``
    does (Lanczos-3 interpolation of the stamp, unit flux) and drawn on the detector's
    pixels without adding the pixel. Resampling PSFEx's grid at the pixels' sub-pixel
    phase gives sums within about 0.5% of 1; a drawn stamp is divided by the sum over the
    model's whole support at its phase (PSFEx models a circle of radius ``n / 2``
    samples, plus Lanczos-3's reach: ~15 px for DECam's 25 x 25 samples), so it holds
    unit flux less the model's own flux beyond the stamp.

    Parameters
    ----------
    parsed : PsfexData
        The model's content.
    data : bytes
        The model file's bytes (stored with an exposure, compared by SHA-256).
    source : str
        The file it was read from, for messages.
    """

    def __init__(
        self, parsed: PsfexData, *, data: bytes | None = None, source: str = "<bytes>"
    ) -> None:
        _refuse_path(PsfexPsf, parsed)
        if not isinstance(parsed, PsfexData):
            raise PsfError(f"PsfexPsf needs a PsfexData, got {type(parsed).__name__}")
        super().__init__(data, source)
        self.parsed = parsed

    def pixel_profile(self, x: float, y: float, jacobian: np.ndarray) -> galsim.GSObject:
        return self._profile(x, y)[0]

    def _profile(self, x: float, y: float) -> tuple[galsim.GSObject, int]:
        """The model at exposure pixel ``(x, y)`` as a unit-flux profile in pixels, and the
        side of its sample grid."""
        array = self.parsed.stamp(x + 1.0, y + 1.0)
        if not (np.all(np.isfinite(array)) and array.sum() > 0):
            raise PsfError(
                f"{self.source}: the PSFEx model at ({x:.2f}, {y:.2f}) does not have a "
                "positive finite sum (polynomial evaluated far outside its fit?)"
            )
        try:
            profile = galsim.InterpolatedImage(
                galsim.Image(array),
                scale=self.parsed.sample,
                flux=1.0,
                x_interpolant=galsim.Lanczos(3),
            )
        except (galsim.GalSimError, ValueError) as err:
            raise PsfError(
                f"{self.source}: PSFEx model failed at ({x:.2f}, {y:.2f}): {err}"
            ) from err
        return profile, max(array.shape)

    def draw(
        self, x: float, y: float, box: Box, jacobian: np.ndarray, center: Center = None
    ) -> np.ndarray:
        profile, side = self._profile(x, y)
        # the profile is in the detector's pixels: drawn on a unit pixel scale
        image = _stamp(box, galsim.PixelScale(1.0))
        stamp = _draw_profile(profile, image, x, y, center, "no_pixel")
        # PSFEx's grid resampled at the pixels' phase sums to 1 only within ~0.5%: divided
        # by the sum over the model's whole support at that phase, a stamp lacks exactly
        # the model's own flux beyond it (psf_flux_outside; docs/shear.md)
        cx, cy = center if center is not None else (x, y)
        reach = (side // 2 + 3) * self.parsed.sample + 1.5  # Lanczos-3 reach
        support = Box(
            x_start=math.floor(cx - reach),
            x_stop=math.ceil(cx + reach) + 1,
            y_start=math.floor(cy - reach),
            y_stop=math.ceil(cy + reach) + 1,
        )
        if box.contains_box(support):
            return stamp / stamp.sum()
        whole = _stamp(support, galsim.PixelScale(1.0))
        return stamp / _draw_profile(profile, whole, x, y, center, "no_pixel").sum()


class PiffPsf(_FileModel):
    """A Piff model, loaded by :func:`cellcoadd.io.read_piff` (optional extra
    ``cellcoadd[piff]``).

    Piff draws with the WCS it was fitted with (stored in the file) in the image
    coordinates of the fit; ``origin`` is the coordinate of the first pixel centre in
    those images: 1 for images read from FITS files (the ``piffify`` executable), 0 for
    GalSim images built with ``xmin=0``. The drawn image includes the pixel (Piff's own
    drawing method: ``"auto"`` for profile models, ``"no_pixel"`` for pixel grids).

    Parameters
    ----------
    model : piff.PSF
        The loaded model (Piff files hold pickled objects: only
        ``read_piff(path, trusted=True)`` loads them).
    data : bytes
        The model file's bytes (stored with an exposure, compared by SHA-256).
    source : str
        The file it was read from, for messages.
    chipnum : int, optional
        Chip of a multi-chip model (default: the only chip).
    origin : int
        0 or 1, see above.
    """

    def __init__(
        self,
        model: Any,
        *,
        data: bytes | None = None,
        source: str = "<bytes>",
        chipnum: int | None = None,
        origin: int = 1,
    ) -> None:
        _refuse_path(PiffPsf, model)
        super().__init__(data, source)
        if origin not in (0, 1) or isinstance(origin, bool):
            raise PsfError(f"{source}: PiffPsf origin must be 0 or 1, got {origin!r}")
        chips = list(getattr(model, "wcs", None) or [])
        if not chips or not hasattr(model, "get_profile"):
            raise PsfError(f"{source}: not a Piff PSF model (no chips with a WCS)")
        if chipnum is None and len(chips) != 1:
            raise PsfError(f"{source}: give chipnum, the model has chips {chips}")
        if chipnum is not None and chipnum not in chips:
            raise PsfError(f"{source}: chipnum {chipnum} is not among the model's {chips}")
        self.model = model
        self.chipnum = chipnum
        self.origin = origin

    def _profile(self, x: float, y: float) -> tuple[galsim.GSObject, str, Any]:
        """Piff's profile at exposure pixel ``(x, y)`` (unit flux checked), its drawing
        method and the local Jacobian of the model's own WCS there."""
        model = self.model
        chipnum = self.chipnum if self.chipnum is not None else list(model.wcs)[0]
        xf, yf = x + self.origin, y + self.origin
        try:
            profile, method = model.get_profile(xf, yf, chipnum=chipnum)
            local = model.wcs[chipnum].local(galsim.PositionD(xf, yf))
        except (galsim.GalSimError, ValueError, KeyError) as err:
            raise PsfError(
                f"{self.source}: Piff model failed at ({x:.2f}, {y:.2f}): {err}"
            ) from err
        check_psf_flux(float(profile.flux), f"{self.source} at ({x:.2f}, {y:.2f})")
        return profile, method, local

    def draw(
        self, x: float, y: float, box: Box, jacobian: np.ndarray, center: Center = None
    ) -> np.ndarray:
        profile, method, local = self._profile(x, y)
        # Piff's profile is on the sky of its own WCS: drawn through that WCS's Jacobian
        image = _stamp(box, local)
        cx, cy = center if center is not None else (x, y)
        return _draw_profile(profile, image, x, y, (cx, cy), method)

    def pixel_profile(self, x: float, y: float, jacobian: np.ndarray) -> galsim.GSObject:
        profile, method, local = self._profile(x, y)
        on_pixels = local.toImage(profile)
        if method == "no_pixel":
            return on_pixels
        if method in ("auto", "fft", "real_space"):  # GalSim adds the pixel for these
            return _with_pixel(on_pixels)
        raise PsfError(f"{self.source}: no profile form for Piff's drawing method {method!r}")


def _with_pixel(profile: galsim.GSObject) -> galsim.GSObject:
    """``profile`` (exposure pixels) convolved with the unit pixel."""
    return galsim.Convolve(profile, galsim.Pixel(1.0))


def as_psf_model(psf: object) -> PsfModel:
    """The :class:`PsfModel` for the PSF forms an exposure accepts.

    A PsfModel is returned as is; a ``galsim.Image`` becomes an :class:`ImagePsf`; a
    GSObject, a :class:`~cellcoadd.model.psf_profiles.VaryingPsf` or a
    :class:`~cellcoadd.model.psf_profiles.GridPsf` (pre-pixel by construction) a
    :class:`GalSimPsf`.

    Raises
    ------
    PsfError
        For anything else, including a bare callable: whether its profiles include the
        pixel must be stated (``GalSimPsf(func)`` for profiles without it,
        ``CallablePsf(func, includes_pixel=...)``); taking a PSFEx or Piff profile as
        pre-pixel would apply the pixel twice.
    """
    if isinstance(psf, PsfModel):
        return psf
    if isinstance(psf, galsim.Image):
        return ImagePsf(psf)
    if isinstance(psf, (galsim.GSObject, VaryingPsf, GridPsf)):
        return GalSimPsf(psf)
    if callable(psf):
        raise PsfError(
            f"a callable PSF ({psf!r}) must state whether its profiles include the pixel: "
            "GalSimPsf(func) for profiles without it (e.g. atmosphere and optics), "
            "CallablePsf(func, includes_pixel=True) for PSFEx- or Piff-like profiles"
        )
    raise PsfError(f"psf must be a PsfModel, a GSObject, a callable or a galsim.Image, got {psf!r}")
