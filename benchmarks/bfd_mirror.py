"""BFD prior with and without mirror images: paired m1, c1, c2 on the same pairs.

For each case the pairs and the templates are made once; the prior is then built from
each template subset with ``mirror`` off and on (``TemplatePrior.from_templates(...,
mirror=...)``), and for each prior the script prints m1, c1, c2 with their jackknife errors,
the paired difference on - off with its jackknife error over the same pairs (the two
priors see the same galaxies and noise, so the difference is far better measured than
either value), the prior's copies and the CPU seconds of building it and of the targets'
P, Q, R. With several disjoint template subsets of one size, the scatter of c2 between
them is the prior's own sampling noise in c2 (the targets are the same), with and without
the mirror. docs/validation.md (BFD, "mirror images in the prior") has the numbers.

Cases::

    high-snr-coadd        S/N 1e4, the targets unsheared as templates (1 rotation), no ring
    high-snr-multi-epoch  partners, g1 = 1e-3 (the high-snr preset's BFD rows)
    coadd                 S/N 10-50, independent templates x 8 rotations, ring partners,
                          g1 = 0.02; subsets of --templates (e.g. 4 x 100 and 1 x 400)

Usage::

    nice -n 10 .venv/bin/python benchmarks/bfd_mirror.py --case high-snr-coadd --n-objects 100
    nice -n 10 .venv/bin/python benchmarks/bfd_mirror.py --case coadd --n-objects 400 \\
        --templates 400 --subsets 100,400
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from typing import Any

import numpy as np

from cellcoadd.pipelines.bfd_validation import bfd_posterior
from cellcoadd.pipelines.shear_validation import _group, run_pairs
from cellcoadd.pipelines.stamp_pairs import bfd_noise_sigma, bfd_templates
from cellcoadd.pipelines.validation_settings import ValidationSettings
from cellcoadd.shear.bfd import bias_from_sums, paired_terms
from cellcoadd.shear.response import jackknife
from cellcoadd.sim import SimConfig

CASES = ("high-snr-coadd", "high-snr-multi-epoch", "coadd")


def case_settings(case: str, seed: int, n_templates: int) -> ValidationSettings:
    """The settings of a case (mirror off)."""
    if case.startswith("high-snr"):
        mode = case.removeprefix("high-snr-")
        return ValidationSettings(
            mode=mode, seed=seed, snr=1.0e4, method="bfd", bfd_template_sample="targets",
            rotated_partners=False, sim=SimConfig(shear=(1.0e-3, 0.0)),
        )  # fmt: skip
    return ValidationSettings(
        mode=case, seed=seed, snr=(10.0, 50.0), method="bfd", bfd_templates=n_templates,
        sim=SimConfig(shear=(0.02, 0.0)),
    )  # fmt: skip


def _biases(sums: np.ndarray, selection: tuple, true_g: float) -> np.ndarray:
    return bias_from_sums(sums, selection, true_g)


def _difference(sums: np.ndarray, split: int, selections: tuple, true_g: float) -> np.ndarray:
    """(m1, c1, c2) of the first run minus those of the second, terms side by side."""
    return _biases(sums[:split], selections[0], true_g) - _biases(
        sums[split:], selections[1], true_g
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", default="high-snr-coadd", choices=CASES)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--n-objects", type=int, default=100)
    parser.add_argument("--templates", type=int, default=100, help="independent templates made")
    parser.add_argument(
        "--subsets", default="100", help="template subset sizes (disjoint subsets of each)"
    )
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--json", help="also write the rows to this JSON file")
    args = parser.parse_args()
    settings = case_settings(args.case, args.seed, args.templates)
    true_g = settings.sim.shear[0]
    start = time.process_time()
    wall = time.perf_counter()
    catalogue = run_pairs(settings, args.n_objects, workers=args.workers, progress=False)
    pairs_cpu = float(catalogue.cpu_seconds.sum())
    group = _group(settings, catalogue)
    t0 = time.process_time()
    templates = bfd_templates(settings, bfd_noise_sigma(settings), catalogue.index.tolist())
    templates_cpu = time.process_time() - t0
    print(
        f"BFD {args.case}, seed {args.seed}, {args.n_objects} pairs (CPU {pairs_cpu:.0f} s), "
        f"{len(templates)} templates (CPU {templates_cpu:.0f} s), g1 = {true_g:g}, "
        f"jackknife group {group}",
        flush=True,
    )
    if settings.bfd_template_sample == "targets":
        subsets = [("targets", templates)]
    else:
        subsets = []
        for size in (int(s) for s in args.subsets.split(",")):
            for k in range(len(templates) // size):
                subsets.append((f"{size}#{k}", templates[k * size : (k + 1) * size]))
    rows: list[dict[str, Any]] = []
    header = (
        f"{'templates':>9} {'mirror':>6} {'copies':>8} {'m1':>20} {'c1':>20} {'c2':>20} "
        f"{'prior+PQR CPU s':>15}"
    )
    print(header)
    for name, subset in subsets:
        runs = {}
        for mirror in (False, True):
            s = settings.model_copy(update={"bfd_mirror": mirror})
            t0 = time.process_time()
            post = bfd_posterior(s, catalogue, subset)
            cpu = time.process_time() - t0
            terms = paired_terms(post.plus, post.minus)
            selection = post.prior.selection_pqr()
            est = functools.partial(_biases, selection=selection, true_g=true_g)
            value, err = jackknife(terms, 100, est, group)
            runs[mirror] = (terms, selection)
            row = {
                "case": args.case, "seed": args.seed, "n_objects": args.n_objects,
                "templates": name, "n_templates": len(subset), "mirror": mirror,
                "copies": len(post.prior.moments), "prior_cpu": cpu,
                **{k: float(v) for k, v in zip(("m1", "c1", "c2"), value, strict=True)},
                **{f"{k}_err": float(v) for k, v in zip(("m1", "c1", "c2"), err, strict=True)},
            }  # fmt: skip
            rows.append(row)
            cells = " ".join(
                f"{row[k]:>+9.2e} +- {row[k + '_err']:<7.1e}" for k in ("m1", "c1", "c2")
            )
            print(f"{name:>9} {str(mirror):>6} {row['copies']:>8} {cells} {cpu:>15.1f}", flush=True)
        both = np.hstack([runs[True][0], runs[False][0]])
        diff = functools.partial(
            _difference, split=runs[True][0].shape[1],
            selections=(runs[True][1], runs[False][1]), true_g=true_g,
        )  # fmt: skip
        d, d_err = jackknife(both, 100, diff, group)
        row = {
            "case": args.case, "seed": args.seed, "templates": name, "mirror": "on - off",
            **{k: float(v) for k, v in zip(("m1", "c1", "c2"), d, strict=True)},
            **{f"{k}_err": float(v) for k, v in zip(("m1", "c1", "c2"), d_err, strict=True)},
        }  # fmt: skip
        rows.append(row)
        cells = " ".join(f"{row[k]:>+9.2e} +- {row[k + '_err']:<7.1e}" for k in ("m1", "c1", "c2"))
        print(f"{name:>9} {'on-off':>6} {'':>8} {cells}", flush=True)
    print(
        f"total CPU of this process {time.process_time() - start:.0f} s (+ the pair workers' "
        f"{pairs_cpu:.0f} s), wall {time.perf_counter() - wall:.0f} s"
    )
    if args.json:
        with open(args.json, "w") as stream:
            json.dump(rows, stream, indent=2)


if __name__ == "__main__":
    main()
