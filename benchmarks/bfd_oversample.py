"""BFD k-space oversampling: the high-S/N check at several zero-padding factors, same pairs.

For each seed, runs BFD's high-S/N check (S/N 10^4, the targets themselves as templates, no
ring partners, g1 = 1e-3: tests/test_validation.py's setup) on the same pairs at each
``--values`` oversampling factor, and prints m1 +- err, the difference from the last
(reference) factor with its jackknife error over the same pairs (the two runs share
galaxies and noise, so the difference is far better measured than either m1), and the CPU
of the pairs, the templates and the prior. docs/validation.md ("k sampling") has the table.

Usage::

    .venv/bin/python benchmarks/bfd_oversample.py                       # coadd, 3 seeds
    .venv/bin/python benchmarks/bfd_oversample.py --mode multi-epoch --seeds 5
    .venv/bin/python benchmarks/bfd_oversample.py --values 1,4 --n-objects 16 --json os.json
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from typing import Any

import numpy as np

from cellcoadd.pipelines.validation.bfd_validation import bfd_posterior
from cellcoadd.pipelines.validation.shear_validation import run_pairs
from cellcoadd.pipelines.validation.validation_settings import ValidationSettings
from cellcoadd.shear.bfd import bias_from_sums, paired_terms
from cellcoadd.shear.response import jackknife
from cellcoadd.sim import SimConfig

#: Input shear of the check (no third-order terms).
SHEAR = 1.0e-3


def run(mode: str, seed: int, oversample: int, n_objects: int, workers: int) -> dict[str, Any]:
    """One factor: the pairs, the prior, and the terms the jackknife needs."""
    settings = ValidationSettings(
        mode=mode, seed=seed, snr=1.0e4, method="bfd", bfd_template_sample="targets",
        bfd_oversample=oversample, rotated_partners=False, sim=SimConfig(shear=(SHEAR, 0.0)),
    )  # fmt: skip
    start = time.perf_counter()
    catalogue = run_pairs(settings, n_objects, workers=workers, progress=False)
    posterior = bfd_posterior(settings, catalogue)
    return {
        "terms": paired_terms(posterior.plus, posterior.minus),
        "selection": posterior.prior.selection_pqr(),
        "pairs_cpu": float(catalogue.cpu_seconds.sum()),
        "prior_cpu": posterior.cpu_seconds,
        "wall": time.perf_counter() - start,
    }


def _m1(sums: np.ndarray, selection: tuple) -> np.ndarray:
    return np.array([bias_from_sums(sums, selection, SHEAR)[0]])


def _difference(sums: np.ndarray, split: int, selections: tuple) -> np.ndarray:
    """m1 of the first run minus m1 of the second, their terms side by side."""
    return _m1(sums[:split], selections[0]) - _m1(sums[split:], selections[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", default="coadd", choices=("coadd", "multi-epoch", "single"))
    parser.add_argument("--seeds", default="3,4,5")
    parser.add_argument("--values", default="1,2,3,4,8", help="factors; the last is the reference")
    parser.add_argument("--n-objects", type=int, default=32)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--json", help="also write the rows to this JSON file")
    args = parser.parse_args()
    values = [int(v) for v in args.values.split(",")]
    reference = values[-1]
    rows = []
    print(f"BFD {args.mode}, S/N 1e4, targets as templates, g1 = {SHEAR:g}, {args.n_objects} pairs")
    print(
        f"{'seed':>4} {'oversample':>10} {'m1':>22} {f'm1 - m1({reference})':>24} "
        f"{'pairs CPU s':>12} {'prior CPU s':>12}"
    )
    for seed in (int(s) for s in args.seeds.split(",")):
        runs = {k: run(args.mode, seed, k, args.n_objects, args.workers) for k in values}
        ref = runs[reference]
        for k in values:
            this = runs[k]
            single = functools.partial(_m1, selection=this["selection"])
            m1, err = jackknife(this["terms"], 100, single)
            both = functools.partial(
                _difference, split=this["terms"].shape[1],
                selections=(this["selection"], ref["selection"]),
            )  # fmt: skip
            d, d_err = jackknife(np.hstack([this["terms"], ref["terms"]]), 100, both)
            row = {
                "mode": args.mode, "seed": seed, "oversample": k, "n_objects": args.n_objects,
                "m1": float(m1[0]), "m1_err": float(err[0]), "diff": float(d[0]),
                "diff_err": float(d_err[0]), "pairs_cpu": this["pairs_cpu"],
                "prior_cpu": this["prior_cpu"],
            }  # fmt: skip
            rows.append(row)
            print(
                f"{seed:>4} {k:>10} {row['m1']:>+10.2e} +- {row['m1_err']:<8.1e} "
                f"{row['diff']:>+11.2e} +- {row['diff_err']:<8.1e} "
                f"{row['pairs_cpu']:>12.1f} {row['prior_cpu']:>12.1f}",
                flush=True,
            )
    if args.json:
        with open(args.json, "w") as stream:
            json.dump(rows, stream, indent=2)


if __name__ == "__main__":
    main()
