"""Shear measurement on cell coadds: metacalibration on plain arrays and its calibration,
observations of cells for shear codes, and the shear-bias validation of the paper.

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
    reconvolution_psf,
)
from cellcoadd.shear.observation import (
    EmptyCellError,
    observation_jacobian,
    to_ngmix,
    to_observation,
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
from cellcoadd.shear.shapes import SHAPE_DTYPE, MetacalFlags
from cellcoadd.shear.stamp_pairs import (
    PairMeasurement,
    ValidationSettings,
    largest_cell_inner,
    measure_pair,
)
from cellcoadd.shear.validation import (
    M_REQUIREMENT,
    PAPER_TABLE1,
    PairCatalogue,
    format_bias_table,
    measure_pairs,
    run_pairs,
    summarize,
    validate_shear,
)

__all__ = [
    "INTERPOLANT",
    "METACAL_TYPES",
    "M_REQUIREMENT",
    "PAPER_CUTS",
    "PAPER_TABLE1",
    "RECONVOLUTION_KINDS",
    "SHAPE_DTYPE",
    "EmptyCellError",
    "MetacalError",
    "MetacalFlags",
    "MetacalImage",
    "PairCatalogue",
    "PairMeasurement",
    "SelectionCuts",
    "ShearResponse",
    "ValidationSettings",
    "format_bias_table",
    "largest_cell_inner",
    "mean_shear",
    "measure_pair",
    "measure_pairs",
    "measure_metacal",
    "measure_shapes",
    "metacal_images",
    "metacal_shears",
    "multiplicative_bias",
    "observation_jacobian",
    "reconvolution_psf",
    "run_pairs",
    "shear_response",
    "stack_results",
    "summarize",
    "to_ngmix",
    "to_observation",
    "validate_shear",
]
