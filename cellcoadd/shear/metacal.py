"""Metacalibration of one image (Sheldon & Huff 2017) with GalSim, on plain arrays.

Conventions
-----------
* ``image`` and ``noise_image`` are 2-D arrays indexed ``[y, x]`` with pixel centres at
  integer 0-based coordinates (see :mod:`cellcoadd.geometry.box`).
* ``psf_image`` is an odd square stamp centred on its central pixel that *includes the
  pixel response* (as a star would look); it is renormalised to sum to 1.
* ``jacobian`` is ``[[du/dx, du/dy], [dv/dx, dv/dy]]`` in arcsec/pixel, GalSim sky
  coordinates (``u`` West, ``v`` North), shared by the image and the PSF stamp.
* Shears are applied, and shapes reported, in those sky coordinates: ``g1 > 0``
  elongates along ``u``, ``g2 > 0`` along ``u = v``.

Procedure
---------
For each type in :data:`METACAL_TYPES` the image is interpolated (Lanczos-15), the
interpolated PSF is deconvolved, the result is sheared by ``(+-step, 0)`` or
``(0, +-step)`` (nothing for ``"noshear"``), reconvolved with one slightly larger
*reconvolution PSF* shared by all types, and drawn back on the original grid with
``method="no_pixel"`` (the deconvolved PSF already took the pixel out, and the
reconvolution PSF stands for PSF x pixel). Because the image and the PSF contain the
same pixel response, the metacal image is the sheared galaxy convolved with the
reconvolution PSF exactly (up to interpolation accuracy).

Correlated-noise correction ("fixnoise"): the noise realization is rotated by 90 degrees
on the pixel grid, put through exactly the same transformation, rotated back and added to
the transformed image. To first order the noise correlations of every metacal image then
no longer depend on the applied shear nor on the PSF anisotropy (exactly so, and fully
symmetric under a 90-degree rotation, when the input noise correlations are themselves
90-degree symmetric, e.g. white noise), so the noise adds no spurious response or
additive shear. The price is twice the noise variance
(:attr:`MetacalImage.variance_factor`). A 90-degree turn of the pixel grid is a 90-degree
turn on the sky when the jacobian is a scaled rotation (or reflection), as for a cell of a
tangent-plane tract.

Shapes of the metacal images (:func:`measure_shapes`) are measured one image at a time by
:mod:`cellcoadd.shear.shapes`, which also defines the record (:data:`SHAPE_DTYPE`) and its
flags (:class:`MetacalFlags`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import galsim
import numpy as np

from cellcoadd.errors import MetacalError
from cellcoadd.geometry.wcs_utils import jacobian_wcs
from cellcoadd.shear.noise_correlation import metacal_noise_covariance
from cellcoadd.shear.shapes import (
    SHAPE_KINDS,
    WMOM_FWHM,
    MetacalFlags,
    ShapeKind,
    empty_record,
    measure_shape,
    measure_wmom,
    psf_T,
)

__all__ = [
    "INTERPOLANT",
    "KSPACE_THRESHOLD",
    "METACAL_TYPES",
    "RECONVOLUTION_KINDS",
    "MetacalError",
    "MetacalImage",
    "ReconvolutionKind",
    "check_arguments",
    "input_flags",
    "measure_metacal",
    "measure_shapes",
    "metacal_images",
    "metacal_shears",
    "noise_covariances",
    "reconvolution_psf",
]

ReconvolutionKind = Literal["gauss", "fitgauss", "dilate"]
RECONVOLUTION_KINDS: tuple[str, ...] = ("gauss", "fitgauss", "dilate")

#: The five metacal image types and the shear ``(g1, g2)`` each applies, in units of step.
METACAL_TYPES: tuple[str, ...] = ("noshear", "1p", "1m", "2p", "2m")
_UNIT_SHEARS: dict[str, tuple[float, float]] = dict(
    zip(METACAL_TYPES, [(0.0, 0.0), (1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)], strict=True)
)

#: High-order interpolant for images and PSF: metacal needs accurate k-space values.
INTERPOLANT = "lanczos15"
#: The "gauss" reconvolution PSF reaches this fraction of its peak in Fourier space at the
#: smallest wavenumber where the PSF (with pixel) does, before dilation.
KSPACE_THRESHOLD = 1.0e-2


@dataclass(frozen=True, eq=False)
class MetacalImage:
    """One metacal image type.

    Attributes
    ----------
    image : ndarray, shape (ny, nx)
        The transformed image, with the rotated transformed noise added when a noise
        image was given.
    psf_image : ndarray, shape (n, n), n odd
        The reconvolution PSF drawn with ``method="no_pixel"`` on the input pixel grid,
        centred on the central pixel, summing to ~1 (it stands for PSF x pixel).
    jacobian : ndarray, shape (2, 2)
        The input jacobian (arcsec/pixel).
    shear : tuple of float
        The applied ``(g1, g2)``.
    noise : ndarray or None
        The correction that was added (transformed noise rotated back), or None.
    variance_factor : float
        Nominal pixel variance of ``image`` in units of the input pixel variance: 2 with
        the noise correction, 1 without. It ignores the (small) change of the pixel
        variance by the deconvolution/reconvolution.
    """

    image: np.ndarray
    psf_image: np.ndarray
    jacobian: np.ndarray
    shear: tuple[float, float]
    noise: np.ndarray | None
    variance_factor: float


def metacal_shears(step: float = 0.01) -> dict[str, tuple[float, float]]:
    """The shear ``(g1, g2)`` applied to each metacal type for a given ``step``."""
    return {name: (step * a, step * b) for name, (a, b) in _UNIT_SHEARS.items()}


def _galsim_wcs(jacobian: np.ndarray) -> galsim.JacobianWCS:
    jac = np.asarray(jacobian, dtype=np.float64)
    if jac.shape != (2, 2) or not np.all(np.isfinite(jac)) or np.linalg.det(jac) == 0.0:
        raise MetacalError(f"jacobian must be a finite non-singular 2x2 array, got {jac!r}")
    return jacobian_wcs(jac)


def _check_psf_image(psf_image: np.ndarray) -> np.ndarray:
    psf = np.asarray(psf_image, dtype=np.float64)
    if psf.ndim != 2 or psf.shape[0] != psf.shape[1] or psf.shape[0] % 2 == 0:
        raise MetacalError(f"psf_image must be an odd square stamp, got shape {psf.shape}")
    total = psf.sum()
    if not np.isfinite(total) or total <= 0.0:
        raise MetacalError("psf_image must be finite with a positive sum")
    return psf / total


def _interpolated(array: np.ndarray, wcs: galsim.BaseWCS) -> galsim.InterpolatedImage:
    # stepk/maxk from the grid and interpolant only: the same Fourier grid for the image,
    # the noise and their rotations (an exactly linear transformation), and no failure on
    # zero-sum inputs such as pure noise.
    gimage = galsim.Image(np.ascontiguousarray(array, dtype=np.float64), xmin=0, ymin=0, wcs=wcs)
    return galsim.InterpolatedImage(
        gimage, x_interpolant=INTERPOLANT, calculate_stepk=False, calculate_maxk=False
    )


def _kspace_sigma(psf: galsim.GSObject, pixel_scale: float) -> float:
    """Sigma (arcsec) of the Gaussian whose Fourier transform hits KSPACE_THRESHOLD at the
    smallest |k| where ``|psf(k)|`` does (in any direction)."""
    n_grid = 512
    k_max = 1.5 * np.pi / pixel_scale  # past the Nyquist wavenumber in every direction
    dk = 2.0 * k_max / n_grid
    kimage = psf.drawKImage(nx=n_grid, ny=n_grid, scale=dk)
    bounds = kimage.bounds
    kx = np.arange(bounds.xmin, bounds.xmax + 1) * dk
    ky = np.arange(bounds.ymin, bounds.ymax + 1) * dk
    k_radius = np.hypot(kx[np.newaxis, :], ky[:, np.newaxis])
    below = np.abs(kimage.array) < KSPACE_THRESHOLD
    k_cut = k_radius[below].min() if below.any() else k_max
    return float(np.sqrt(-2.0 * np.log(KSPACE_THRESHOLD)) / k_cut)


def reconvolution_psf(
    psf_image: np.ndarray,
    jacobian: np.ndarray,
    step: float = 0.01,
    kind: ReconvolutionKind = "gauss",
) -> galsim.GSObject:
    """The reconvolution PSF (unit flux, arcsec) shared by all metacal types.

    Parameters
    ----------
    psf_image : ndarray
        Odd square PSF stamp including the pixel response.
    jacobian : ndarray, shape (2, 2)
        ``[[du/dx, du/dy], [dv/dx, dv/dy]]`` in arcsec/pixel.
    step : float
        Metacal shear step; every choice is dilated by ``1 + 2 |step|`` so that the
        sheared, deconvolved image is still suppressed where the PSF has no power.
    kind : {"gauss", "fitgauss", "dilate"}
        ``"gauss"`` (default): a round Gaussian sized in Fourier space, falling to
        ``KSPACE_THRESHOLD`` of its peak at the smallest wavenumber where the PSF does, so
        it never asks for power the PSF has lost. ``"fitgauss"``: a round Gaussian with
        the PSF's adaptive-moments size ``sigma = det(M)^(1/4)``. ``"dilate"``: the PSF
        itself, dilated (keeps the PSF anisotropy, so additive leakage stays).

    Returns
    -------
    galsim.GSObject
    """
    wcs = _galsim_wcs(jacobian)
    psf = _check_psf_image(psf_image)
    dilation = 1.0 + 2.0 * abs(step)
    if kind == "dilate":
        return _interpolated(psf, wcs).dilate(dilation)
    if kind == "gauss":
        pixel_scale = float(np.sqrt(abs(np.linalg.det(np.asarray(jacobian, dtype=float)))))
        sigma = _kspace_sigma(_interpolated(psf, wcs), pixel_scale)
    elif kind == "fitgauss":
        moments = galsim.hsm.FindAdaptiveMom(
            galsim.Image(psf, xmin=0, ymin=0, wcs=wcs), strict=False, use_sky_coords=True
        )
        if moments.moments_status != 0:
            raise MetacalError(f"adaptive moments of the PSF failed: {moments.error_message}")
        sigma = moments.moments_sigma
    else:
        raise MetacalError(f"unknown reconvolution PSF kind {kind!r}")
    return galsim.Gaussian(sigma=sigma * dilation)


def _draw_psf(reconv: galsim.GSObject, wcs: galsim.BaseWCS, min_size: int) -> np.ndarray:
    # Grow the stamp, if needed, to hold the reconvolution PSF out to ~5 sigma.
    scale = np.sqrt(abs(wcs.pixelArea()))
    half_width = int(np.ceil(5.0 * reconv.calculateMomentRadius(scale=scale) / scale))
    size = max(min_size, 2 * half_width + 1)
    stamp = galsim.Image(size, size, xmin=0, ymin=0, wcs=wcs, dtype=np.float64)
    reconv.drawImage(image=stamp, method="no_pixel")
    return stamp.array.copy()


def _transform(
    interpolated: galsim.GSObject,
    deconvolution: galsim.GSObject,
    reconv: galsim.GSObject,
    shear: tuple[float, float],
    shape: tuple[int, int],
    wcs: galsim.BaseWCS,
) -> np.ndarray:
    obj = galsim.Convolve(interpolated, deconvolution)
    if shear != (0.0, 0.0):
        obj = obj.shear(g1=shear[0], g2=shear[1])
    obj = galsim.Convolve(obj, reconv)
    out = galsim.Image(shape[1], shape[0], xmin=0, ymin=0, wcs=wcs, dtype=np.float64)
    obj.drawImage(image=out, method="no_pixel")
    return out.array.copy()


def metacal_images(
    image: np.ndarray,
    psf_image: np.ndarray,
    noise_image: np.ndarray | None,
    jacobian: np.ndarray,
    step: float = 0.01,
    psf: ReconvolutionKind = "gauss",
    types: Sequence[str] = METACAL_TYPES,
    reconv: galsim.GSObject | None = None,
) -> dict[str, MetacalImage]:
    """Make the metacal images of ``image``.

    Parameters
    ----------
    image : ndarray, shape (ny, nx)
        Background-subtracted image (any flux unit); pixel centres at integer coordinates.
    psf_image : ndarray, shape (n, n), n odd
        PSF including the pixel response, centred on the central pixel (renormalised).
    noise_image : ndarray, shape (ny, nx), or None
        A noise realization with the statistics (correlations included) of the image
        noise, independent of it; None disables the correlated-noise correction (useful
        for noise-free images only).
    jacobian : ndarray, shape (2, 2)
        ``[[du/dx, du/dy], [dv/dx, dv/dy]]`` in arcsec/pixel, for image and PSF.
    step : float
        Shear step applied for the ``1p/1m/2p/2m`` types.
    psf : {"gauss", "fitgauss", "dilate"}
        Reconvolution PSF; see :func:`reconvolution_psf`.
    types : sequence of str
        Subset of :data:`METACAL_TYPES` to make.
    reconv : galsim.GSObject, optional
        The reconvolution PSF (unit flux, arcsec) to use instead of the one ``psf`` picks
        for this image: multi-epoch metacalibration reconvolves every epoch with one
        common PSF (:func:`cellcoadd.shear.multi_epoch.common_reconvolution_psf`). It must
        be at least as large as this image's own choice.

    Returns
    -------
    dict of str to MetacalImage

    Raises
    ------
    MetacalError
        Malformed inputs: shapes, non-finite pixels, unusable PSF or jacobian.
    """
    image, noise_image = check_arguments(image, psf_image, noise_image, jacobian, step, psf, types)
    if not np.all(np.isfinite(image)) or (
        noise_image is not None and not np.all(np.isfinite(noise_image))
    ):
        raise MetacalError("image or noise_image has non-finite pixels")
    wcs = _galsim_wcs(jacobian)
    psf_normalised = _check_psf_image(psf_image)
    if reconv is None:
        reconv = reconvolution_psf(psf_normalised, jacobian, step=step, kind=psf)
    deconvolution = galsim.Deconvolve(_interpolated(psf_normalised, wcs))
    reconv_image = _draw_psf(reconv, wcs, psf_normalised.shape[0])
    shears = metacal_shears(step)

    image_interp = _interpolated(image, wcs)
    if noise_image is not None:
        rotated = np.rot90(noise_image, k=1)
        noise_interp = _interpolated(rotated, wcs)

    result: dict[str, MetacalImage] = {}
    for name in types:
        transformed = _transform(
            image_interp, deconvolution, reconv, shears[name], image.shape, wcs
        )
        correction = None
        if noise_image is not None:
            noise_out = _transform(
                noise_interp, deconvolution, reconv, shears[name], rotated.shape, wcs
            )
            correction = np.rot90(noise_out, k=-1).copy()
            transformed = transformed + correction
        result[name] = MetacalImage(
            image=transformed,
            psf_image=reconv_image,
            jacobian=np.array(jacobian, dtype=np.float64),
            shear=shears[name],
            noise=correction,
            variance_factor=2.0 if noise_image is not None else 1.0,
        )
    return result


def noise_covariances(metacal: Mapping[str, MetacalImage]) -> dict[str, np.ndarray | None]:
    """The noise autocovariance each metacal type's S/N uses: one for every type.

    It is the noshear image's, measured from its correction
    (:func:`~cellcoadd.shear.noise_correlation.metacal_noise_covariance`). The noise of
    the five images has the same statistics whatever the applied shear (the correction
    makes it so), so one estimate serves them all; separate estimates, each from its own
    correction on one small stamp, would differ by their estimation noise, and that noise
    alone would move objects across an S/N cut between the ``1p`` and ``1m`` images,
    which the selection response then pays for in variance (on coadds at S/N 10-50: twice
    as many objects crossing ``S/N > 10`` between them, and a per-pair scatter of ``m1``
    of 1.35 instead of 0.98 with that cut; see docs/validation.md). Without a noshear image
    with a correction, each type's own (None where it has no correction: white noise).
    """
    reference = metacal.get("noshear")
    if reference is not None and reference.noise is not None:
        shared = metacal_noise_covariance(reference.noise)
        return {name: shared for name in metacal}
    return {
        name: None if image.noise is None else metacal_noise_covariance(image.noise)
        for name, image in metacal.items()
    }


def measure_shapes(
    metacal: Mapping[str, MetacalImage],
    noise_sigma: float,
    guess_centroid: tuple[float, float] | None = None,
    guess_sigma: float | None = None,
    shape: ShapeKind = "admom",
    weight_fwhm: float = WMOM_FWHM,
) -> dict[str, np.ndarray]:
    """Shapes of each metacal image.

    With ``shape="admom"`` the ellipticity estimator is the adaptive-moments reduced shear
    ``g = (a - b) / (a + b) * (cos 2 phi, sin 2 phi)`` (GalSim ``observed_shape``) in sky
    coordinates; for a round Gaussian galaxy its response to shear is
    ``R11 = R22 = T_gal / (T_gal + T_psf) = 1 - T_psf / T``. With ``shape="wmom"`` it is
    the polarisation of the moments in a fixed round Gaussian weight of FWHM
    ``weight_fwhm`` arcsec centred on ``guess_centroid`` (:func:`~cellcoadd.shear.shapes.
    measure_wmom`); ``T`` and ``T_psf`` are then both weighted moments.

    Parameters
    ----------
    metacal : mapping of str to MetacalImage
        Output of :func:`metacal_images`.
    noise_sigma : float
        Per-pixel noise standard deviation of the *input* image (image units). The S/N
        uses the covariance of the metacal images' noise, measured from the noshear
        image's correction and the same for every type (:func:`noise_covariances`:
        correlated by the coadd's resampling and by the reconvolution), or, without a
        correction, white noise of variance ``variance_factor * noise_sigma**2``; zero
        then gives an infinite S/N.
    guess_centroid : (x, y), optional
        0-based pixel position to start from (default: the image centre).
    guess_sigma : float, optional
        Starting Gaussian sigma in pixels (default: 1.5 x that of the reconvolution PSF).
    shape : {"admom", "wmom"}
        Adaptive moments, or moments in a fixed Gaussian weight.
    weight_fwhm : float
        FWHM (arcsec) of the ``wmom`` weight.

    Returns
    -------
    dict of str to ndarray
        For each type, a length-1 structured array of :data:`SHAPE_DTYPE`. Failures are
        flagged (:class:`MetacalFlags`), never raised; failed fields are NaN.
    """
    if shape not in SHAPE_KINDS:
        raise MetacalError(f"unknown shape {shape!r}; known: {SHAPE_KINDS}")
    if not (np.isfinite(weight_fwhm) and weight_fwhm > 0.0):
        raise MetacalError(f"weight_fwhm must be positive (arcsec), got {weight_fwhm}")
    results: dict[str, np.ndarray] = {}
    covariances = noise_covariances(metacal)
    for name, mc in metacal.items():
        wcs = _galsim_wcs(mc.jacobian)
        covariance = covariances[name]
        if shape == "wmom":
            variance = mc.variance_factor * noise_sigma**2
            record = measure_wmom(
                mc.image, wcs, variance, guess_centroid, weight_fwhm, noise_covariance=covariance
            )
            record["T_psf"] = psf_T(mc.psf_image, wcs, weight_fwhm)
            results[name] = record
            continue
        T_psf = psf_T(mc.psf_image, wcs)
        pixel_area = abs(wcs.pixelArea())
        if guess_sigma is None:
            sigma = 1.5 * np.sqrt(T_psf / 2.0 / pixel_area) if np.isfinite(T_psf) else 5.0
        else:
            sigma = guess_sigma
        record = measure_shape(
            mc.image, wcs, mc.variance_factor * noise_sigma**2, guess_centroid, sigma,
            noise_covariance=covariance,
        )  # fmt: skip
        record["T_psf"] = T_psf
        if not np.isfinite(T_psf):
            record["flags"] |= MetacalFlags.PSF_FAILED
        results[name] = record
    return results


def measure_metacal(
    image: np.ndarray,
    psf_image: np.ndarray,
    noise_image: np.ndarray | None,
    jacobian: np.ndarray,
    noise_sigma: float,
    step: float = 0.01,
    psf: ReconvolutionKind = "gauss",
    guess_centroid: tuple[float, float] | None = None,
    guess_sigma: float | None = None,
    shape: ShapeKind = "admom",
    weight_fwhm: float = WMOM_FWHM,
) -> dict[str, np.ndarray]:
    """Metacal images of ``image`` and their shapes in one call.

    Arguments are those of :func:`metacal_images` and :func:`measure_shapes`. Problems
    with the pixel *values* (non-finite pixels, an unusable PSF, a GalSim failure) are
    flagged in every type rather than raised; malformed arguments (shapes, jacobian,
    step) still raise :class:`MetacalError`.

    Returns
    -------
    dict of str to ndarray
        For each of :data:`METACAL_TYPES`, a length-1 structured array of
        :data:`SHAPE_DTYPE`.
    """
    image, noise_image = check_arguments(image, psf_image, noise_image, jacobian, step, psf)
    if shape not in SHAPE_KINDS:
        raise MetacalError(f"unknown shape {shape!r}; known: {SHAPE_KINDS}")
    flag = input_flags(image, psf_image, noise_image)
    if not flag:
        try:
            images = metacal_images(image, psf_image, noise_image, jacobian, step=step, psf=psf)
        except MetacalError:  # arguments were checked: the PSF moments failed
            flag = MetacalFlags.PSF_FAILED
        except galsim.GalSimError:
            flag = MetacalFlags.TRANSFORM_FAILED
    if flag:
        return {name: empty_record(flag) for name in METACAL_TYPES}
    return measure_shapes(images, noise_sigma, guess_centroid, guess_sigma, shape, weight_fwhm)


def input_flags(image: np.ndarray, psf_image: np.ndarray, noise_image: np.ndarray | None) -> int:
    """:class:`MetacalFlags` of unusable pixel values: ``NONFINITE`` for non-finite pixels
    in the image or the noise image, ``PSF_FAILED`` for a PSF stamp without a finite
    positive sum; 0 when metacalibration can run."""
    if not np.all(np.isfinite(image)) or (
        noise_image is not None and not np.all(np.isfinite(noise_image))
    ):
        return int(MetacalFlags.NONFINITE)
    psf_sum = float(np.sum(psf_image))
    if not np.isfinite(psf_sum) or psf_sum <= 0.0:
        return int(MetacalFlags.PSF_FAILED)
    return 0


def check_arguments(
    image: np.ndarray,
    psf_image: np.ndarray,
    noise_image: np.ndarray | None,
    jacobian: np.ndarray,
    step: float,
    kind: str,
    types: Sequence[str] = METACAL_TYPES,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Raise :class:`MetacalError` on malformed arguments of :func:`metacal_images` (shapes,
    a singular jacobian, the step, an unknown reconvolution PSF kind or type); return
    ``image`` and ``noise_image`` as float64."""
    image = np.asarray(image, dtype=np.float64)
    if image.ndim != 2 or image.size == 0:
        raise MetacalError(f"image must be a non-empty 2-D array, got shape {image.shape}")
    if noise_image is not None:
        noise_image = np.asarray(noise_image, dtype=np.float64)
        if noise_image.shape != image.shape:
            raise MetacalError(
                f"noise_image shape {noise_image.shape} differs from image shape {image.shape}"
            )
    psf_shape = np.shape(psf_image)
    if len(psf_shape) != 2 or psf_shape[0] != psf_shape[1] or psf_shape[0] % 2 == 0:
        raise MetacalError(f"psf_image must be an odd square stamp, got shape {psf_shape}")
    _galsim_wcs(jacobian)
    if not 0.0 < abs(step) < 0.1:
        raise MetacalError(f"step must be small and non-zero, got {step}")
    if kind not in RECONVOLUTION_KINDS:
        raise MetacalError(f"unknown reconvolution PSF {kind!r}; known: {RECONVOLUTION_KINDS}")
    unknown = set(types) - set(METACAL_TYPES)
    if unknown:
        raise MetacalError(f"unknown metacal types {sorted(unknown)}; known: {METACAL_TYPES}")
    return image, noise_image
