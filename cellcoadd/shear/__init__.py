"""Shear measurement on cell coadds: metacalibration on plain arrays (one image, or several
epochs of an object measured jointly) and its calibration, and observations of cells for
shear codes (the shear-bias validation of the paper is in
:mod:`cellcoadd.pipelines`).

See ``docs/shear.md`` for the conventions (PSF includes the pixel; jacobian in
arcsec/pixel, GalSim ``u`` West / ``v`` North) and usage, ``docs/validation.md`` for the
bias validation.
"""

from cellcoadd.shear.metacal import (
    INTERPOLANT,
    METACAL_TYPES,
    RECONVOLUTION_KINDS,
    MetacalError,
    MetacalImage,
    measure_metacal,
    measure_shapes,
    metacal_images,
    metacal_shears,
    noise_covariances,
    reconvolution_psf,
)
from cellcoadd.shear.multi_epoch import (
    MetacalEpoch,
    common_reconvolution_psf,
    measure_joint_shapes,
    measure_metacal_multi_epoch,
    multi_epoch_images,
)
from cellcoadd.shear.noise_correlation import (
    gaussian_weight,
    noise_correlation,
    noise_covariance,
    noise_power_spectrum,
    snr_correction,
    variance_factor,
    weighted_flux_variance,
)
from cellcoadd.shear.observation import (
    EmptyCellError,
    observation_jacobian,
    to_ngmix,
    to_observation,
)
from cellcoadd.shear.response import (
    PAPER_CUTS,
    WMOM_CUTS,
    SelectionCuts,
    ShearResponse,
    bias_by_selection,
    cuts_for_shape,
    mean_shear,
    multiplicative_bias,
    shear_response,
    stack_results,
)
from cellcoadd.shear.shapes import SHAPE_DTYPE, SHAPE_KINDS, WMOM_FWHM, MetacalFlags

__all__ = [
    "INTERPOLANT",
    "METACAL_TYPES",
    "PAPER_CUTS",
    "WMOM_CUTS",
    "RECONVOLUTION_KINDS",
    "SHAPE_DTYPE",
    "SHAPE_KINDS",
    "WMOM_FWHM",
    "EmptyCellError",
    "MetacalError",
    "MetacalFlags",
    "MetacalEpoch",
    "MetacalImage",
    "SelectionCuts",
    "bias_by_selection",
    "cuts_for_shape",
    "ShearResponse",
    "common_reconvolution_psf",
    "gaussian_weight",
    "mean_shear",
    "measure_joint_shapes",
    "measure_metacal",
    "measure_metacal_multi_epoch",
    "measure_shapes",
    "metacal_images",
    "metacal_shears",
    "multi_epoch_images",
    "multiplicative_bias",
    "noise_correlation",
    "noise_covariances",
    "noise_covariance",
    "noise_power_spectrum",
    "observation_jacobian",
    "reconvolution_psf",
    "shear_response",
    "snr_correction",
    "stack_results",
    "to_ngmix",
    "to_observation",
    "variance_factor",
    "weighted_flux_variance",
]
