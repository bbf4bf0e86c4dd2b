"""Survey runs: every band and tract of an exposure index built on dask (or here), with
one ledger (resume, staleness), reports and coverage figures.

* :mod:`~cellcoadd.pipelines.survey.run`: :func:`run_survey`, :func:`run_tract`;
* :mod:`~cellcoadd.pipelines.survey.plan`: tracts from the index, patches per tract;
* :mod:`~cellcoadd.pipelines.survey.tasks`: what a worker does for one patch;
* :mod:`~cellcoadd.pipelines.survey.records`: the typed patch records;
* :mod:`~cellcoadd.pipelines.survey.ledger`: the ledger and the lock of an output
  directory;
* :mod:`~cellcoadd.pipelines.survey.report`: ``report.json`` and the coverage figures.
"""

from cellcoadd.pipelines.survey.plan import PatchPlan, TractPlan, candidate_tracts, plan_tract
from cellcoadd.pipelines.survey.records import PatchKey, PatchRecord, PatchState, PatchSummary
from cellcoadd.pipelines.survey.run import RunResult, output_path, run_survey, run_tract

__all__ = [
    "PatchKey",
    "PatchPlan",
    "PatchRecord",
    "PatchState",
    "PatchSummary",
    "RunResult",
    "TractPlan",
    "candidate_tracts",
    "output_path",
    "plan_tract",
    "run_survey",
    "run_tract",
]
