"""Measurements of one validation object on its epochs: single epoch and multi-epoch.

What :func:`cellcoadd.pipelines.validation.stamp_pairs.measure_pair` runs in ``mode="single"``
(:func:`measure_single_epoch`) and ``mode="multi-epoch"`` (:func:`measure_multi_epoch`),
and the BFD record all modes share.

**Per-epoch inputs** (:class:`EpochGeometry`, the same for both members of a pair): the
object's sky position mapped through each epoch's WCS (the reference pixel), the local
jacobian there and the epoch's PSF drawn at that position through the local WCS, pixel
response included, on an odd ``build.psf_size`` stamp centred on its central pixel.

**Multi-epoch metacalibration** (:mod:`cellcoadd.shear.multi_epoch`): every epoch is
deconvolved by its own PSF, sheared, reconvolved by one common round PSF (the largest of
the epochs' own choices; it depends on the PSFs only, so it is made once per pair) with
its own correlated-noise correction (an independent noise realization of the same
level per epoch), and one joint shape is measured on the epochs' own pixels (joint
inverse-variance weighted moments, :mod:`cellcoadd.shear.joint_shapes`).

**Multi-epoch BFD**: each epoch's Fourier data in sky coordinates about the object's sky
position, divided by its own PSF transform, with its white-noise power of the known
level; the epochs are summed (:func:`cellcoadd.shear.bfd.sum_epochs`: moments and
covariances add up) and the moments measured about the joint null-centroid point.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import galsim
import numpy as np

from cellcoadd.errors import MetacalError
from cellcoadd.geometry.box import Box
from cellcoadd.model.exposure import Exposure
from cellcoadd.pipelines.validation.validation_settings import ValidationSettings
from cellcoadd.shear import anacal_adapter, bfd
from cellcoadd.shear.metacal import measure_metacal
from cellcoadd.shear.multi_epoch import (
    MetacalEpoch,
    common_reconvolution_psf,
    measure_metacal_multi_epoch,
)
from cellcoadd.sim.stamps import StampObject

#: One BFD measurement per row: ``flags`` (0: good; :data:`BFD_NOT_CENTRED`,
#: :data:`BFD_FAILED`, ``stamp_pairs.NO_COADD``), the even moments ``F, R, E1, E2``, their
#: covariance, the odd-moment covariance, the centre offset (arcsec) and the flux S/N.
BFD_DTYPE = np.dtype(
    [
        ("flags", "i4"),
        ("even", "f8", (4,)),
        ("cov_even", "f8", (4, 4)),
        ("cov_odd", "f8", (2, 2)),
        ("centre", "f8", (2,)),
        ("snr", "f8"),
    ]
)
BFD_NOT_CENTRED = 1
BFD_FAILED = 2


def epoch_psf_image(exposure: Exposure, x: float, y: float, size: int) -> np.ndarray:
    """The PSF of ``exposure`` at pixel ``(x, y)`` on an odd ``size`` x ``size`` stamp.

    Drawn through the exposure's local jacobian at ``(x, y)``, with the pixel response,
    centred on the stamp's central pixel: the form metacal takes.
    """
    centre = float(size // 2)
    return exposure.draw_psf(x, y, Box.from_shape((size, size)), center=(centre, centre))


@dataclass(frozen=True, eq=False)
class EpochGeometry:
    """Where an object is in each of its epochs, and the PSF there.

    Attributes
    ----------
    centres : list of (float, float)
        0-based pixel position of the object's sky position in each epoch.
    jacobians : list of ndarray, shape (2, 2)
        Local jacobian (arcsec/pixel) at each centre.
    psfs : list of ndarray
        Each epoch's PSF at its centre (:func:`epoch_psf_image`).
    """

    centres: list[tuple[float, float]]
    jacobians: list[np.ndarray]
    psfs: list[np.ndarray]

    @classmethod
    def of(cls, obj: StampObject, psf_size: int) -> EpochGeometry:
        """Map ``obj``'s sky position through each exposure's WCS and draw its PSFs."""
        centres, jacobians, psfs = [], [], []
        for exposure in obj.exposures:
            x, y = (float(c) for c in exposure.wcs.all_world2pix(obj.ra, obj.dec, 0))
            centres.append((x, y))
            jacobians.append(exposure.local_jacobian(x, y))
            psfs.append(epoch_psf_image(exposure, x, y, psf_size))
        return cls(centres, jacobians, psfs)


def bfd_record(moments: bfd.Moments | None) -> dict[str, np.ndarray]:
    """``{"bfd": row}``: a length-1 :data:`BFD_DTYPE` row of ``moments`` (None: failed)."""
    record = np.zeros(1, dtype=BFD_DTYPE)
    if moments is None:
        record["flags"] = BFD_FAILED
        return {"bfd": record}
    record["flags"] = 0 if moments.converged else BFD_NOT_CENTRED
    record["even"] = moments.even
    if moments.cov_even is not None and moments.cov_odd is not None:
        record["cov_even"] = moments.cov_even
        record["cov_odd"] = moments.cov_odd
    record["centre"] = moments.centre
    record["snr"] = moments.snr
    return {"bfd": record}


def bfd_measurement(
    settings: ValidationSettings, image: np.ndarray, psf: np.ndarray, jacobian: np.ndarray,
    centre: tuple[float, float], **noise: object,
) -> dict[str, np.ndarray]:  # fmt: skip
    """BFD moments of one image (``noise``: ``noise_images=`` or ``noise_variance=``)."""
    try:
        moments = bfd.bfd_moments(
            image, psf, jacobian, weight=bfd.KSigmaWeight(sigma=settings.bfd_sigma),
            centre=centre, oversample=settings.bfd_oversample, **noise,  # type: ignore[arg-type]
        )  # fmt: skip
    except bfd.BfdError:
        return bfd_record(None)
    return bfd_record(moments)


def bfd_epoch_sum(
    settings: ValidationSettings,
    exposures: Sequence[Exposure],
    geometry: EpochGeometry,
    noise_variance: float | None,
) -> bfd.KData:
    """The summed Fourier data of an object's epochs (multi-epoch BFD, module docstring).

    ``noise_variance`` (counts^2, the same in every epoch) gives each epoch's white-noise
    power; None for noise-free templates. Raises :class:`~cellcoadd.errors.BfdError`
    when an epoch cannot be measured.
    """
    weight = bfd.KSigmaWeight(sigma=settings.bfd_sigma)
    data = [
        bfd.fourier_data(
            exposure.image,
            psf,
            jac,
            noise_variance=noise_variance,
            weight=weight,
            centre=centre,
            oversample=settings.bfd_oversample,
        )
        for exposure, psf, jac, centre in zip(
            exposures, geometry.psfs, geometry.jacobians, geometry.centres, strict=True
        )
    ]
    return bfd.sum_epochs(data)


def measure_single_epoch(
    settings: ValidationSettings,
    obj: StampObject,
    exposure: Exposure,
    sigma: float,
    noise: np.ndarray,
) -> dict[str, np.ndarray]:
    """Measure the first epoch alone (``mode="single"``).

    Parameters
    ----------
    settings : ValidationSettings
        The run's settings (method, shape, ...).
    obj : StampObject
        The object (its first epoch's truth position).
    exposure : Exposure
        The first epoch, with noise.
    sigma : float
        Its pixel noise level, counts.
    noise : ndarray
        A noise realization of the epoch's shape and level, independent of its noise
        (metacal's correction, AnaCal's noise bias); BFD uses white noise of ``sigma``.
    """
    x, y = obj.epochs[0].position
    if settings.method == "bfd":
        centre = (int(round(x)), int(round(y)))
        return bfd_measurement(
            settings, exposure.image, epoch_psf_image(exposure, *centre, settings.build.stamp_size),
            exposure.local_jacobian(*centre), centre, noise_variance=sigma**2,
        )  # fmt: skip
    psf = epoch_psf_image(exposure, x, y, settings.build.stamp_size)
    if settings.method == "anacal":
        record = anacal_adapter.measure_fpfs(
            exposure.image, psf, noise, exposure.local_jacobian(x, y), sigma**2, (x, y),
            sigma_arcsec=settings.anacal_sigma,
        )  # fmt: skip
        return {"anacal": record}
    return measure_metacal(
        exposure.image,
        psf,
        noise,
        exposure.local_jacobian(x, y),
        noise_sigma=sigma,
        step=settings.step,
        psf=settings.reconvolution_psf,
        guess_centroid=(x, y),
        shape=settings.shape,
        weight_fwhm=settings.wmom_fwhm,
    )


def common_psf(settings: ValidationSettings, geometry: EpochGeometry) -> galsim.GSObject | None:
    """The multi-epoch metacal reconvolution PSF of an object (None when it cannot be made:
    the measurement then flags the failure)."""
    try:
        return common_reconvolution_psf(
            geometry.psfs, geometry.jacobians, settings.step, settings.reconvolution_psf
        )
    except (MetacalError, galsim.GalSimError):  # flagged by each member's measurement
        return None


def measure_multi_epoch(
    settings: ValidationSettings,
    exposures: Sequence[Exposure],
    geometry: EpochGeometry,
    sigma: float,
    noise: np.ndarray,
    reconv: galsim.GSObject | None = None,
) -> dict[str, np.ndarray]:
    """Measure all epochs jointly (``mode="multi-epoch"``, metacal or BFD).

    Parameters
    ----------
    settings : ValidationSettings
        The run's settings.
    exposures : sequence of Exposure
        The object's epochs, with noise.
    geometry : EpochGeometry
        Reference pixels, jacobians and PSFs of the epochs.
    sigma : float
        Pixel noise level of every epoch, counts.
    noise : ndarray, shape (n_epochs, ny, nx)
        Unit-variance noise realizations, one per epoch, independent of the image noise
        (metacal's correlated-noise correction, scaled by ``sigma``).
    reconv : galsim.GSObject, optional
        The common reconvolution PSF (:func:`common_psf`), made here when not given.
    """
    if settings.method == "bfd":
        try:
            data = bfd_epoch_sum(settings, exposures, geometry, sigma**2)
        except bfd.BfdError:
            return bfd_record(None)
        return bfd_record(bfd.measure_moments(data))
    epochs = [
        MetacalEpoch(e.image, psf, sigma * plane, jac, sigma, centre)
        for e, psf, jac, centre, plane in zip(
            exposures, geometry.psfs, geometry.jacobians, geometry.centres, noise, strict=True
        )
    ]
    return measure_metacal_multi_epoch(
        epochs,
        step=settings.step,
        psf=settings.reconvolution_psf,
        shape=settings.shape,
        weight_fwhm=settings.wmom_fwhm,
        reconv=reconv,
    )


__all__ = [
    "BFD_DTYPE",
    "BFD_FAILED",
    "BFD_NOT_CENTRED",
    "EpochGeometry",
    "bfd_epoch_sum",
    "bfd_measurement",
    "bfd_record",
    "common_psf",
    "epoch_psf_image",
    "measure_multi_epoch",
    "measure_single_epoch",
]
