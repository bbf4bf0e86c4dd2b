"""End-to-end runs that combine simulations, the builder and shear measurement.

* :mod:`cellcoadd.pipelines.demo`: what ``cellcoadd demo`` (``make demo``) runs;
* :mod:`cellcoadd.pipelines.stamp_pairs`: the paper's paired stamp simulations, built
  into cells and measured;
* :mod:`cellcoadd.pipelines.shear_validation`: the shear-bias validation over many pairs
  (``cellcoadd validate-shear``).
"""

from cellcoadd.pipelines.shear_validation import (
    M_REQUIREMENT,
    PAPER_TABLE1,
    PairCatalogue,
    format_bias_table,
    measure_pairs,
    run_pairs,
    summarize,
    validate_shear,
)
from cellcoadd.pipelines.stamp_pairs import (
    PairMeasurement,
    ValidationSettings,
    largest_cell_inner,
    measure_pair,
)

__all__ = [
    "M_REQUIREMENT",
    "PAPER_TABLE1",
    "PairCatalogue",
    "PairMeasurement",
    "ValidationSettings",
    "format_bias_table",
    "largest_cell_inner",
    "measure_pair",
    "measure_pairs",
    "run_pairs",
    "summarize",
    "validate_shear",
]
