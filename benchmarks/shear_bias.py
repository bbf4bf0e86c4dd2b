"""Metacal shear bias on cell coadds vs a single epoch, beside the paper's Table 1.

Runs :func:`cellcoadd.pipelines.validate_shear` at realistic S/N (10-50 by default) in coadd
and single-epoch modes and prints m1, c1, c2 with jackknife errors, the objects used, the
CPU time and what a run at the paper's precision (sigma_m = 4e-4) would cost. The default
size takes ~15 minutes on 2 cores (~0.45 CPU s per pair and mode).

Usage::

    .venv/bin/python benchmarks/shear_bias.py                      # ~15 min, 2 workers
    .venv/bin/python benchmarks/shear_bias.py --n-objects 600 --json bias.json
    .venv/bin/python benchmarks/shear_bias.py --modes coadd --snr 10000 --n-objects 400
    .venv/bin/python benchmarks/shear_bias.py --scheduler tcp://127.0.0.1:8786 --n-objects 100000
"""

from __future__ import annotations

import argparse
import json
import math

from cellcoadd.pipelines import format_bias_table, validate_shear

#: sigma(m1) of the paper's metacal rows.
PAPER_SIGMA_M = 4.0e-4


def _snr(text: str) -> float | tuple[float, float] | None:
    if text == "none":
        return None
    values = [float(part) for part in text.split(",")]
    return values[0] if len(values) == 1 else (values[0], values[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-objects", type=int, default=2000, help="pairs per mode")
    parser.add_argument("--snr", default="10,50", help="LO,HI, VALUE or 'none' (sim noise)")
    parser.add_argument("--modes", default="coadd,single", help="comma-separated")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--scheduler", help="dask.distributed scheduler address")
    parser.add_argument("--coadd-pixel-scale", type=float, default=0.2)
    parser.add_argument("--json", help="also write the results to this JSON file")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args()

    results = []
    for mode in args.modes.split(","):
        result = validate_shear(
            mode,  # type: ignore[arg-type]
            n_objects=args.n_objects,
            snr=_snr(args.snr),
            seed=args.seed,
            workers=args.workers,
            scheduler=args.scheduler,
            coadd_pixel_scale=args.coadd_pixel_scale,
            progress=not args.quiet,
        )
        results.append(result)
    print(format_bias_table(results))
    print()
    for result in results:
        per_pair = result["cpu_seconds"] / result["n_objects"]
        # sigma(m1) scales as 1 / sqrt(N): pairs and CPU for the paper's precision
        needed = result["n_objects"] * (result["m1_err"] / PAPER_SIGMA_M) ** 2
        print(
            f"{result['mode']}: {result['n_objects']} pairs, {result['n_used']} used, "
            f"wall {result['wall_seconds']:.0f} s, CPU {result['cpu_seconds']:.0f} s "
            f"({per_pair:.2f} s/pair, {1.0 / per_pair:.2f} pairs per CPU s); "
            f"sigma_m = {PAPER_SIGMA_M:g} needs ~{needed:.2g} pairs, "
            f"~{needed * per_pair / 3600.0:.3g} CPU hours"
            + ("" if math.isfinite(needed) else " (no estimate)")
        )
    if args.json:
        with open(args.json, "w") as stream:
            json.dump(results, stream, indent=2, default=float)


if __name__ == "__main__":
    main()
