"""End-to-end runs that combine simulations, the builder and shear measurement.

* :mod:`cellcoadd.pipelines.demo`: what ``cellcoadd demo`` (``make demo``) runs;
* :mod:`cellcoadd.pipelines.validation.stamp_pairs`: the paper's paired stamp simulations,
  built into cells and measured (or measured on the epochs themselves:
  :mod:`cellcoadd.pipelines.validation.epoch_measurements`);
* :mod:`cellcoadd.pipelines.survey`: survey runs from an exposure index on
  dask.distributed (``cellcoadd run``: every band and tract), with the run ledger
  (:mod:`~cellcoadd.pipelines.survey.ledger`) and reports
  (:mod:`~cellcoadd.pipelines.survey.report`);
* :mod:`cellcoadd.pipelines.validation.shear_validation`: the shear-bias validation over
  many pairs (``cellcoadd validate-shear``; BFD's and AnaCal's summaries in
  :mod:`~cellcoadd.pipelines.validation.bfd_validation` and
  :mod:`~cellcoadd.pipelines.validation.anacal_validation`, the per-row presets of
  ``benchmarks/shear_bias.py`` in :mod:`~cellcoadd.pipelines.validation.bias_presets`),
  all in the sub-package :mod:`cellcoadd.pipelines.validation`.

The names below are imported from their modules on first use, so that importing one
pipeline module (say :mod:`cellcoadd.pipelines.simulation_files` for ``cellcoadd
simulate``) does not load the others and what they need (numba, the builder).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from cellcoadd._lazy import lazy_exports

#: public name -> module that defines it
_EXPORTS: dict[str, str] = {
    "M_REQUIREMENT": "cellcoadd.pipelines.validation.bias_table",
    "PAPER_TABLE1": "cellcoadd.pipelines.validation.bias_table",
    "PAPER_TABLE1_ROWS": "cellcoadd.pipelines.validation.bias_table",
    "PairCatalogue": "cellcoadd.pipelines.validation.stamp_pairs",
    "format_bias_table": "cellcoadd.pipelines.validation.bias_table",
    "cut_comparison": "cellcoadd.pipelines.validation.shear_validation",
    "measure_pairs": "cellcoadd.pipelines.validation.shear_validation",
    "run_pairs": "cellcoadd.pipelines.validation.shear_validation",
    "summarize": "cellcoadd.pipelines.validation.shear_validation",
    "validate_shear": "cellcoadd.pipelines.validation.shear_validation",
    "EpochGeometry": "cellcoadd.pipelines.validation.epoch_measurements",
    "PairMeasurement": "cellcoadd.pipelines.validation.stamp_pairs",
    "ValidationSettings": "cellcoadd.pipelines.validation.validation_settings",
    "largest_cell_inner": "cellcoadd.pipelines.validation.validation_settings",
    "measure_pair": "cellcoadd.pipelines.validation.stamp_pairs",
    "measure_multi_epoch": "cellcoadd.pipelines.validation.epoch_measurements",
    "measure_single_epoch": "cellcoadd.pipelines.validation.epoch_measurements",
    "RunResult": "cellcoadd.pipelines.survey",
    "plan_tract": "cellcoadd.pipelines.survey",
    "run_survey": "cellcoadd.pipelines.survey",
    "run_tract": "cellcoadd.pipelines.survey",
}

__all__ = [
    "M_REQUIREMENT",
    "PAPER_TABLE1",
    "PAPER_TABLE1_ROWS",
    "EpochGeometry",
    "PairCatalogue",
    "PairMeasurement",
    "RunResult",
    "ValidationSettings",
    "cut_comparison",
    "format_bias_table",
    "largest_cell_inner",
    "measure_multi_epoch",
    "measure_pair",
    "measure_pairs",
    "measure_single_epoch",
    "plan_tract",
    "run_pairs",
    "run_survey",
    "run_tract",
    "summarize",
    "validate_shear",
]


__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS)


if TYPE_CHECKING:  # the same names, for type checkers and IDEs
    from cellcoadd.pipelines.survey import RunResult, plan_tract, run_survey, run_tract
    from cellcoadd.pipelines.validation.bias_table import (
        M_REQUIREMENT,
        PAPER_TABLE1,
        PAPER_TABLE1_ROWS,
        format_bias_table,
    )
    from cellcoadd.pipelines.validation.epoch_measurements import (
        EpochGeometry,
        measure_multi_epoch,
        measure_single_epoch,
    )
    from cellcoadd.pipelines.validation.shear_validation import (
        cut_comparison,
        measure_pairs,
        run_pairs,
        summarize,
        validate_shear,
    )
    from cellcoadd.pipelines.validation.stamp_pairs import (
        PairCatalogue,
        PairMeasurement,
        measure_pair,
    )
    from cellcoadd.pipelines.validation.validation_settings import (
        ValidationSettings,
        largest_cell_inner,
    )
