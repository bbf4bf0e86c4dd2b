"""Long Monte Carlo runs of the coadd S/N loss (paper Fig. 4) and the LSST case.

Runs the paper's setting (dsigma_p/sigma_p = 0.1) and the LSST-like scatter (0.3), with
deterministic and random per-epoch PSF sizes, and prints the measured, exact and toy
variance ratios. Takes a few minutes with the default number of trials.

Usage::

    .venv/bin/python benchmarks/snr_loss_mc.py --trials 50000 --json results.json
"""

from __future__ import annotations

import argparse
import json
import time

from cellcoadd.analysis import lsst_snr_loss, monte_carlo_ratio


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=50_000, help="noise realizations per R")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", help="also write all tables to this JSON file")
    args = parser.parse_args()

    runs = {
        "paper_quantiles": {"dsigma_over_sigma": 0.1},
        "paper_random_sizes": {"dsigma_over_sigma": 0.1, "psf_sizes": "random", "n_psf_sets": 50},
        "lsst_scatter": {"dsigma_over_sigma": 0.3, "resolutions": (0.0, 0.2, 0.4, 0.6, 0.8)},
    }
    results = {}
    for name, settings in runs.items():
        start = time.perf_counter()
        table = monte_carlo_ratio(n_trials=args.trials, seed=args.seed, **settings)
        print(f"[{name}] {time.perf_counter() - start:.1f} s")
        print(table.to_text(), end="\n\n")
        results[name] = table.to_dict()
    for n_epochs in (10, 20, 50):
        lsst = lsst_snr_loss(resolutions=(0.0, 0.5, 0.8), n_epochs=n_epochs)
        rows = {key: [round(float(v), 5) for v in values] for key, values in lsst.items()}
        print(f"LSST exact, {n_epochs} epochs: {rows}")
        results[f"lsst_exact_{n_epochs}_epochs"] = rows
    if args.json:
        with open(args.json, "w") as stream:
            json.dump(results, stream, indent=2)


if __name__ == "__main__":
    main()
