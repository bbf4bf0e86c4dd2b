"""Shear measurement on cell coadds: metacalibration on plain arrays and its calibration.

See ``docs/shear.md`` for the conventions (PSF includes the pixel; jacobian in
arcsec/pixel, GalSim ``u`` West / ``v`` North) and usage.
"""

from cellcoadd.shear.metacal import (
    INTERPOLANT,
    METACAL_TYPES,
    RECONVOLUTION_KINDS,
    SHAPE_DTYPE,
    MetacalError,
    MetacalFlags,
    MetacalImage,
    measure_metacal,
    measure_shapes,
    metacal_images,
    metacal_shears,
    reconvolution_psf,
)
from cellcoadd.shear.response import (
    PAPER_CUTS,
    SelectionCuts,
    ShearResponse,
    mean_shear,
    multiplicative_bias,
    shear_response,
    stack_results,
)

__all__ = [
    "INTERPOLANT",
    "METACAL_TYPES",
    "PAPER_CUTS",
    "RECONVOLUTION_KINDS",
    "SHAPE_DTYPE",
    "MetacalError",
    "MetacalFlags",
    "MetacalImage",
    "SelectionCuts",
    "ShearResponse",
    "mean_shear",
    "measure_metacal",
    "measure_shapes",
    "metacal_images",
    "metacal_shears",
    "multiplicative_bias",
    "reconvolution_psf",
    "shear_response",
    "stack_results",
]
