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
``PsfexPsf``       a PSFEx ``.psf`` file                          detector px   included
``PiffPsf``        a Piff model file (extra ``cellcoadd[piff]``)  Piff's WCS    included
=================  =============================================  ============  =========

:func:`as_psf_model` turns the forms an :class:`~cellcoadd.model.exposure.Exposure`
accepts into one of these: a bare GSObject or callable is a ``GalSimPsf`` (the callable
form is pre-pixel), a ``galsim.Image`` an ``ImagePsf``.
"""

from __future__ import annotations

import hashlib
import os
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any

import galsim
import numpy as np

from cellcoadd.errors import PsfError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.wcs_utils import jacobian_wcs


def _stamp(box: Box, wcs: galsim.BaseWCS) -> galsim.ImageD:
    """A zeroed GalSim image over ``box`` (0-based exposure pixels) with ``wcs``."""
    bounds = galsim.BoundsI(box.x_start, box.x_stop - 1, box.y_start, box.y_stop - 1)
    return galsim.ImageD(bounds, wcs=wcs)


def _user_profile(func: Callable[[float, float], Any], x: float, y: float) -> galsim.GSObject:
    """``func(x, y)``, which must be a GSObject; any failure of user code is a PsfError."""
    try:
        profile = func(x, y)
    except Exception as err:  # user code may fail in any way: the input is rejected
        raise PsfError(f"the PSF callable failed at ({x:.2f}, {y:.2f}): {err!r}") from err
    if not isinstance(profile, galsim.GSObject):
        raise PsfError(f"the PSF callable returned {type(profile).__name__}, not a GSObject")
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
        self.profile = profile

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


class ImagePsf(PsfModel):
    """A constant PSF given as a stamp that includes the pixel response.

    Parameters
    ----------
    image : galsim.Image or ndarray
        Odd square stamp sampled on the exposure's pixel grid, centred on its central
        pixel; interpolated with Lanczos-3 to the requested sub-pixel centre.
    """

    includes_pixel = True

    def __init__(self, image: galsim.Image | np.ndarray):
        array = np.asarray(image.array if isinstance(image, galsim.Image) else image)
        ny, nx = array.shape if array.ndim == 2 else (0, 0)
        if ny != nx or ny % 2 == 0:
            raise PsfError(f"an image PSF must be an odd square stamp, got shape {array.shape}")
        if not (np.all(np.isfinite(array)) and array.sum() > 0):
            raise PsfError("an image PSF must be finite with a positive sum")
        self.image = image if isinstance(image, galsim.Image) else galsim.Image(array)

    def draw(
        self, x: float, y: float, box: Box, jacobian: np.ndarray, center: Center = None
    ) -> np.ndarray:
        wcs = jacobian_wcs(jacobian)
        stamp = galsim.Image(self.image.array, wcs=wcs)
        profile = galsim.InterpolatedImage(stamp, x_interpolant="lanczos3")
        return _draw_profile(profile, _stamp(box, wcs), x, y, center, "no_pixel")


class _FileModel(PsfModel):
    """A PSF model read from a file, held as the file's bytes (picklable, storable)."""

    includes_pixel = True

    def __init__(self, path: str | os.PathLike[str] | None = None, *, data: bytes | None = None):
        if (path is None) == (data is None):
            raise PsfError(f"{type(self).__name__} needs a path or data, not both")
        if path is not None:
            try:
                with open(path, "rb") as file:
                    data = file.read()
            except OSError as err:
                raise PsfError(f"{path}: cannot read the PSF model file ({err})") from err
        self.source = os.fspath(path) if path is not None else "<bytes>"
        self.data: bytes = data  # type: ignore[assignment]
        self.sha256 = hashlib.sha256(self.data).hexdigest()
        self._model: Any = None

    @property
    def model(self) -> Any:
        """The library's model object, read from :attr:`data` on first use."""
        if self._model is None:
            try:
                self._model = self._load()
            except PsfError:
                raise
            except Exception as err:  # the reading library's errors are of many types
                raise PsfError(
                    f"{self.source}: not a valid {type(self).__name__} model file ({err})"
                ) from err
        return self._model

    @abstractmethod
    def _load(self) -> Any: ...

    def __getstate__(self) -> dict[str, Any]:
        # the library object is rebuilt from the bytes in the receiving process
        return {**self.__dict__, "_model": None}

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, _FileModel)
            and type(other) is type(self)
            and other.sha256 == self.sha256
        )

    def __hash__(self) -> int:
        return hash((type(self).__name__, self.sha256))


class PsfexPsf(_FileModel):
    """A PSFEx model (``.psf`` file), read with GalSim's ``galsim.des.DES_PSFEx``.

    PSFEx samples the effective PSF (pixel included) every ``PSF_SAMP`` pixels, with
    polynomials in SExtractor's 1-based ``X_IMAGE``/``Y_IMAGE``: the model is evaluated
    at ``(x + 1, y + 1)`` for 0-based ``(x, y)`` and drawn on the detector's pixels
    without adding the pixel. Stamps sum to 1 within about 0.5% depending on the
    sub-pixel phase (the resampling of PSFEx's grid); the coadd PSF is normalised after
    averaging.

    Parameters
    ----------
    path : path-like, optional
        The ``.psf`` file.
    data : bytes, optional
        Its contents instead (as stored in exposure files).
    """

    def _load(self) -> Any:
        import io

        import galsim.des
        from astropy.io import fits

        with fits.open(io.BytesIO(self.data)) as hdus:
            hdu = hdus[1]
            return galsim.des.DES_PSFEx(hdu)

    def draw(
        self, x: float, y: float, box: Box, jacobian: np.ndarray, center: Center = None
    ) -> np.ndarray:
        try:
            profile = self.model.getPSF(galsim.PositionD(x + 1.0, y + 1.0))
        except (galsim.GalSimError, ValueError, IndexError) as err:
            raise PsfError(
                f"{self.source}: PSFEx model failed at ({x:.2f}, {y:.2f}): {err}"
            ) from err
        # the profile is in the detector's pixels: drawn on a unit pixel scale
        image = _stamp(box, galsim.PixelScale(1.0))
        return _draw_profile(profile, image, x, y, center, "no_pixel")


class PiffPsf(_FileModel):
    """A Piff model file (optional extra ``cellcoadd[piff]``).

    Piff draws with the WCS it was fitted with (stored in the file) in the image
    coordinates of the fit; ``origin`` is the coordinate of the first pixel centre in
    those images: 1 for images read from FITS files (the ``piffify`` executable), 0 for
    GalSim images built with ``xmin=0``. The drawn image includes the pixel (Piff's own
    drawing method: ``"auto"`` for profile models, ``"no_pixel"`` for pixel grids).

    Parameters
    ----------
    path : path-like, optional
        The Piff model file.
    data : bytes, optional
        Its contents instead (as stored in exposure files).
    chipnum : int, optional
        Chip of a multi-chip model (default: the only chip).
    origin : int
        0 or 1, see above.

    Notes
    -----
    Piff files hold pickled WCS objects: read only model files you trust.
    """

    def __init__(
        self,
        path: str | os.PathLike[str] | None = None,
        *,
        data: bytes | None = None,
        chipnum: int | None = None,
        origin: int = 1,
    ):
        super().__init__(path, data=data)
        if origin not in (0, 1):
            raise PsfError(f"PiffPsf origin must be 0 or 1, got {origin!r}")
        self.chipnum = chipnum
        self.origin = origin

    def _load(self) -> Any:
        import tempfile

        try:
            import piff
        except ImportError as err:
            raise PsfError(
                "reading Piff models needs the optional extra: pip install 'cellcoadd[piff]'"
            ) from err
        # piff reads from a file name only
        with tempfile.NamedTemporaryFile(suffix=".piff") as file:
            file.write(self.data)
            file.flush()
            return piff.read(file.name)

    def draw(
        self, x: float, y: float, box: Box, jacobian: np.ndarray, center: Center = None
    ) -> np.ndarray:
        model = self.model
        chipnum = self.chipnum
        if chipnum is None:
            chips = list(model.wcs)
            if len(chips) != 1:
                raise PsfError(f"{self.source}: give chipnum, the model has chips {chips}")
            chipnum = chips[0]
        xf, yf = x + self.origin, y + self.origin
        try:
            profile, method = model.get_profile(xf, yf, chipnum=chipnum)
            local = model.wcs[chipnum].local(galsim.PositionD(xf, yf))
        except (galsim.GalSimError, ValueError, KeyError) as err:
            raise PsfError(
                f"{self.source}: Piff model failed at ({x:.2f}, {y:.2f}): {err}"
            ) from err
        # Piff's profile is on the sky of its own WCS: drawn through that WCS's Jacobian
        image = _stamp(box, local)
        cx, cy = center if center is not None else (x, y)
        return _draw_profile(profile, image, x, y, (cx, cy), method)


def as_psf_model(psf: object) -> PsfModel:
    """The :class:`PsfModel` for the PSF forms an exposure accepts.

    A PsfModel is returned as is; a ``galsim.Image`` becomes an :class:`ImagePsf`; a
    GSObject or any other callable a :class:`GalSimPsf` (pre-pixel).

    Raises
    ------
    PsfError
        For anything else.
    """
    if isinstance(psf, PsfModel):
        return psf
    if isinstance(psf, galsim.Image):
        return ImagePsf(psf)
    if isinstance(psf, galsim.GSObject) or callable(psf):
        return GalSimPsf(psf)
    raise PsfError(f"psf must be a PsfModel, a GSObject, a callable or a galsim.Image, got {psf!r}")
