"""Multi-epoch metacalibration: every epoch of an object in its own pixels, one joint shape.

The reference against which the paper compares coadds (Table 1, "multi-epoch" rows). For
one object observed in ``K`` epochs (:class:`MetacalEpoch`: image, PSF stamp with the
pixel response, noise realization, jacobian, noise level, and the pixel position of the
object's reference sky position):

1. **One reconvolution PSF for all epochs** (:func:`common_reconvolution_psf`): each
   epoch's own choice (:func:`~cellcoadd.shear.metacal.reconvolution_psf`, a round
   Gaussian) is made and the largest is kept, so it suppresses the noise where any epoch's
   PSF has lost power. Reconvolving every epoch by the same PSF makes the epochs' metacal
   images views of the same sheared, reconvolved galaxy. ``"dilate"`` (which keeps each
   PSF's anisotropy) has no common choice and is refused.
2. **Per-epoch metacal images** (:func:`multi_epoch_images`): each epoch is deconvolved by
   its own PSF, sheared in sky coordinates (the five types of
   :data:`~cellcoadd.shear.metacal.METACAL_TYPES`) and reconvolved by the common PSF, with
   its own correlated-noise correction (its own noise realization through the same
   transformation, turned by 90 degrees): :func:`~cellcoadd.shear.metacal.metacal_images`
   with ``reconv`` given.
3. **One joint shape per type** (:func:`measure_joint_shapes`): the epochs' weighted sums
   in one sky-coordinate Gaussian weight, combined with inverse-variance weights
   (:mod:`cellcoadd.shear.joint_shapes`: fixed round weight for ``wmom``, joint adaptive
   moments for ``admom``); ``T_psf`` is the common reconvolution PSF measured the same way.

The records are :data:`~cellcoadd.shear.shapes.SHAPE_DTYPE`, so the response, selection
response and cuts of :mod:`cellcoadd.shear.response` apply unchanged. With one epoch the
result is that of :func:`~cellcoadd.shear.metacal.measure_metacal` (exactly for ``wmom``,
to ~1e-6 for ``admom``, whose iteration is ours rather than HSM's).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import galsim
import numpy as np

from cellcoadd.errors import MetacalError
from cellcoadd.shear.joint_shapes import EpochPixels, joint_admom, joint_psf_T, joint_wmom
from cellcoadd.shear.metacal import (
    METACAL_TYPES,
    MetacalImage,
    ReconvolutionKind,
    check_arguments,
    input_flags,
    metacal_images,
    noise_covariances,
    reconvolution_psf,
)
from cellcoadd.shear.shapes import (
    SHAPE_KINDS,
    WMOM_FWHM,
    MetacalFlags,
    ShapeKind,
    empty_record,
)

__all__ = [
    "ROUND_KINDS",
    "MetacalEpoch",
    "common_reconvolution_psf",
    "measure_joint_shapes",
    "measure_metacal_multi_epoch",
    "multi_epoch_images",
]

#: Reconvolution PSF kinds with one common (round) choice for all epochs.
ROUND_KINDS: tuple[str, ...] = ("gauss", "fitgauss")
_NOT_ROUND = (
    "multi-epoch metacalibration needs one round reconvolution PSF for all epochs "
    "('gauss' or 'fitgauss'), got {!r}"
)


@dataclass(frozen=True, eq=False)
class MetacalEpoch:
    """One epoch of an object for multi-epoch metacalibration.

    Attributes
    ----------
    image : ndarray, shape (ny, nx)
        Background-subtracted image (any flux unit, the same for every epoch), indexed
        ``[y, x]``, pixel centres at integer 0-based coordinates.
    psf_image : ndarray, shape (n, n), n odd
        The epoch's PSF at the object, pixel response included, centred on its central
        pixel, on the epoch's pixel grid.
    noise_image : ndarray, shape (ny, nx), or None
        A noise realization with the statistics of the epoch's noise, independent of it
        (None: no correlated-noise correction, for noise-free images only).
    jacobian : ndarray, shape (2, 2)
        ``[[du/dx, du/dy], [dv/dx, dv/dy]]`` at the object, arcsec/pixel.
    noise_sigma : float
        Pixel noise standard deviation of ``image`` (image units).
    centre : (float, float)
        0-based pixel position ``(x, y)`` of the object's reference sky position (the same
        sky point in every epoch, e.g. a detection mapped through each epoch's WCS).
    """

    image: np.ndarray
    psf_image: np.ndarray
    noise_image: np.ndarray | None
    jacobian: np.ndarray
    noise_sigma: float
    centre: tuple[float, float]


def common_reconvolution_psf(
    psf_images: Sequence[np.ndarray],
    jacobians: Sequence[np.ndarray],
    step: float = 0.01,
    kind: ReconvolutionKind = "gauss",
) -> galsim.Gaussian:
    """The round reconvolution PSF shared by all epochs: the largest of their own choices.

    Parameters
    ----------
    psf_images : sequence of ndarray
        Each epoch's PSF stamp (pixel response included, centred on its central pixel).
    jacobians : sequence of ndarray, shape (2, 2)
        Each epoch's jacobian (arcsec/pixel).
    step : float
        Metacal shear step (the choices are dilated by ``1 + 2 |step|``).
    kind : {"gauss", "fitgauss"}
        How each epoch's Gaussian is sized (:func:`~cellcoadd.shear.metacal.
        reconvolution_psf`).

    Returns
    -------
    galsim.Gaussian
        Unit flux, sigma in arcsec.

    Raises
    ------
    MetacalError
        ``kind="dilate"``, no epoch, or an epoch's PSF moments fail (``fitgauss``).
    """
    if kind not in ROUND_KINDS:
        raise MetacalError(_NOT_ROUND.format(kind))
    if len(psf_images) == 0 or len(psf_images) != len(jacobians):
        raise MetacalError("need one PSF stamp and one jacobian per epoch, at least one")
    sigmas = [
        reconvolution_psf(psf, jac, step=step, kind=kind).sigma
        for psf, jac in zip(psf_images, jacobians, strict=True)
    ]
    return galsim.Gaussian(sigma=float(max(sigmas)))


def multi_epoch_images(
    epochs: Sequence[MetacalEpoch],
    step: float = 0.01,
    psf: ReconvolutionKind = "gauss",
    reconv: galsim.GSObject | None = None,
) -> list[dict[str, MetacalImage]]:
    """Each epoch's metacal images, all reconvolved by one common PSF.

    Parameters
    ----------
    epochs : sequence of MetacalEpoch
        The object's epochs.
    step : float
        Metacal shear step.
    psf : {"gauss", "fitgauss"}
        How the common reconvolution PSF is chosen (ignored when ``reconv`` is given).
    reconv : galsim.GSObject, optional
        The common reconvolution PSF, when already known (it depends on the PSFs only:
        the two members of a +g/-g pair share it).

    Returns
    -------
    list of dict of str to MetacalImage
        One dict per epoch, keyed by :data:`~cellcoadd.shear.metacal.METACAL_TYPES`.
    """
    if reconv is None:
        reconv = common_reconvolution_psf(
            [e.psf_image for e in epochs], [e.jacobian for e in epochs], step, psf
        )
    return [
        metacal_images(
            e.image, e.psf_image, e.noise_image, e.jacobian, step=step, psf=psf, reconv=reconv
        )
        for e in epochs
    ]


def measure_joint_shapes(
    images: Sequence[Mapping[str, MetacalImage]],
    epochs: Sequence[MetacalEpoch],
    shape: ShapeKind = "admom",
    weight_fwhm: float = WMOM_FWHM,
    guess_sigma: float | None = None,
) -> dict[str, np.ndarray]:
    """One joint shape per metacal type from every epoch's metacal images.

    Parameters
    ----------
    images : sequence of mapping of str to MetacalImage
        :func:`multi_epoch_images`, one mapping per epoch, aligned with ``epochs``.
    epochs : sequence of MetacalEpoch
        The epochs (for their reference pixel and noise level).
    shape : {"admom", "wmom"}
        Joint adaptive moments, or joint moments in a fixed round weight of FWHM
        ``weight_fwhm`` arcsec (:mod:`cellcoadd.shear.joint_shapes`).
    weight_fwhm : float
        FWHM (arcsec) of the ``wmom`` weight.
    guess_sigma : float, optional
        Starting sigma (arcsec) of the adaptive weight (default: 1.5 x that of the
        reconvolution PSF, as single-image metacal).

    Returns
    -------
    dict of str to ndarray
        For each type, a length-1 :data:`~cellcoadd.shear.shapes.SHAPE_DTYPE` array.
        Each epoch's pixel variance is ``variance_factor * noise_sigma**2`` (its
        weight); the S/N uses the covariance of each epoch's noise, measured from its
        noshear correction and the same for every type, as in
        :func:`cellcoadd.shear.metacal.measure_shapes`.
    """
    if shape not in SHAPE_KINDS:
        raise MetacalError(f"unknown shape {shape!r}; known: {SHAPE_KINDS}")
    if len(images) != len(epochs) or not epochs:
        raise MetacalError("need the metacal images of every epoch, at least one")
    fwhm = weight_fwhm if shape == "wmom" else None
    results: dict[str, np.ndarray] = {}
    T_psf: float | None = None
    covariances = [noise_covariances(per_epoch) for per_epoch in images]  # per epoch, by type
    for name in images[0]:
        pixels = [
            EpochPixels.from_image(
                per_epoch[name].image,
                epoch.jacobian,
                epoch.centre,
                per_epoch[name].variance_factor * epoch.noise_sigma**2,
                by_type[name],
            )
            for per_epoch, epoch, by_type in zip(images, epochs, covariances, strict=True)
        ]
        if T_psf is None:  # the same reconvolution PSF in every type
            T_psf = joint_psf_T([per_epoch[name].psf_image for per_epoch in images], pixels, fwhm)
        if shape == "wmom":
            record = joint_wmom(pixels, weight_fwhm)
        else:
            if guess_sigma is not None:
                sigma = guess_sigma
            elif np.isfinite(T_psf):
                sigma = 1.5 * np.sqrt(T_psf / 2.0)
            else:
                sigma = 5.0 * np.sqrt(pixels[0].pixel_area)
            record = joint_admom(pixels, sigma)
        record["T_psf"] = T_psf
        if not np.isfinite(T_psf):
            record["flags"] |= MetacalFlags.PSF_FAILED
        results[name] = record
    return results


def measure_metacal_multi_epoch(
    epochs: Sequence[MetacalEpoch],
    step: float = 0.01,
    psf: ReconvolutionKind = "gauss",
    shape: ShapeKind = "admom",
    weight_fwhm: float = WMOM_FWHM,
    reconv: galsim.GSObject | None = None,
) -> dict[str, np.ndarray]:
    """Multi-epoch metacalibration of one object in one call (see the module docstring).

    Parameters
    ----------
    epochs : sequence of MetacalEpoch
        The object's epochs (at least one).
    step, psf, shape, weight_fwhm
        As for :func:`~cellcoadd.shear.metacal.measure_metacal` (``psf`` must be round:
        ``"gauss"`` or ``"fitgauss"``).
    reconv : galsim.GSObject, optional
        The common reconvolution PSF, when already known (:func:`common_reconvolution_psf`).

    Returns
    -------
    dict of str to ndarray
        For each of :data:`~cellcoadd.shear.metacal.METACAL_TYPES`, a length-1
        :data:`~cellcoadd.shear.shapes.SHAPE_DTYPE` array. Unusable pixel values in any
        epoch (non-finite pixels, a PSF stamp without a positive sum), a failed PSF
        measurement or a GalSim failure flag every type; malformed arguments raise
        :class:`~cellcoadd.errors.MetacalError`.
    """
    if not epochs:
        raise MetacalError("multi-epoch metacalibration needs at least one epoch")
    if shape not in SHAPE_KINDS:
        raise MetacalError(f"unknown shape {shape!r}; known: {SHAPE_KINDS}")
    if psf not in ROUND_KINDS and reconv is None:
        raise MetacalError(_NOT_ROUND.format(psf))
    for e in epochs:
        check_arguments(e.image, e.psf_image, e.noise_image, e.jacobian, step, psf)
    flag = 0
    for e in epochs:
        flag |= input_flags(e.image, e.psf_image, e.noise_image)
    if not flag:
        try:
            images = multi_epoch_images(epochs, step=step, psf=psf, reconv=reconv)
        except MetacalError:  # arguments were checked: a PSF's moments failed
            flag = MetacalFlags.PSF_FAILED
        except galsim.GalSimError:
            flag = MetacalFlags.TRANSFORM_FAILED
    if flag:
        return {name: empty_record(flag) for name in METACAL_TYPES}
    return measure_joint_shapes(images, epochs, shape, weight_fwhm)
