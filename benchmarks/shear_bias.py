"""Shear bias of metacal and BFD on cell coadds vs multi-epoch, in Table 1's layout.

Runs :func:`cellcoadd.pipelines.validate_shear` for the rows of the paper's Table 1
(metacal coadd, metacal multi-epoch, BFD coadd, BFD multi-epoch) and AnaCal on coadds,
and prints m1 +- err, c1, c2, the pairs used and the CPU time beside the paper's values
("-" where the paper has none), then what the paper's precision (sigma_m = 4e-4) would
cost. ``single`` rows (the first epoch alone, e.g. ``metacal-single``) can be added with
``--rows``. The default is small (200 pairs per row at S/N 10-50, about 15 CPU minutes);
the error on m1 is then ~0.1 (it falls as 1/sqrt(N)).

Usage::

    .venv/bin/python benchmarks/shear_bias.py                      # ~15 CPU min, 2 workers
    .venv/bin/python benchmarks/shear_bias.py --n-objects 2000 --json bias.json
    .venv/bin/python benchmarks/shear_bias.py --rows metacal-coadd --snr 10000 --n-objects 400
    .venv/bin/python benchmarks/shear_bias.py --rows metacal-multi-epoch,metacal-single
    .venv/bin/python benchmarks/shear_bias.py --shape wmom --rows metacal-coadd,metacal-multi-epoch
    .venv/bin/python benchmarks/shear_bias.py --scheduler tcp://127.0.0.1:8786 --n-objects 100000
"""

from __future__ import annotations

import argparse
import json
import math

from cellcoadd.pipelines import validate_shear
from cellcoadd.pipelines.shear_validation import PAPER_TABLE1_ROWS

#: sigma(m1) of the paper's metacal rows.
PAPER_SIGMA_M = 4.0e-4
#: Default rows: the paper's Table 1 and AnaCal on coadds.
ROWS = ("metacal-coadd", "metacal-multi-epoch", "bfd-coadd", "bfd-multi-epoch", "anacal-coadd")
#: Rows that can be asked for with --rows.
ALL_ROWS = (*ROWS, "metacal-single", "bfd-single", "anacal-single")
_NAMES = {"metacal": "metacal", "bfd": "BFD", "anacal": "AnaCal"}


def _snr(text: str) -> float | tuple[float, float] | None:
    if text == "none":
        return None
    values = [float(part) for part in text.split(",")]
    return values[0] if len(values) == 1 else (values[0], values[1])


def table(results: list[dict]) -> str:
    """Table 1's layout: one line per row, ours beside the paper's m1."""
    header = (
        f"{'sample':<22} {'m1 (ours)':>20} {'m1 (paper)':>18} {'c1':>18} {'c2':>18} "
        f"{'pairs used/N':>13} {'CPU s':>8}"
    )
    lines = [header, "-" * len(header)]
    for r in results:
        method, mode = r["method"], r["mode"]
        paper = PAPER_TABLE1_ROWS.get((method, mode))
        paper_text = "-" if paper is None else f"{paper[0]:+.4f} +- {paper[1]:.4f}"
        name = f"{_NAMES[method]} {mode}"
        lines.append(
            f"{name:<22} {r['m1']:+.4f} +- {r['m1_err']:.4f}   {paper_text:>16} "
            f"{r['c1']:+.4f}+-{r['c1_err']:.4f} {r['c2']:+.4f}+-{r['c2_err']:.4f} "
            f"{str(r['n_used']) + '/' + str(r['n_objects']):>13} {r['cpu_seconds']:>8.0f}"
        )
    lines.append("'single': the first epoch alone (not in the paper); requirement |m1| < 0.001")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-objects", type=int, default=200, help="pairs per row")
    parser.add_argument("--snr", default="10,50", help="LO,HI, VALUE or 'none' (sim noise)")
    parser.add_argument("--rows", default=",".join(ROWS), help=f"comma-separated of {ALL_ROWS}")
    parser.add_argument("--shape", default="admom", choices=("admom", "wmom"))
    parser.add_argument("--bfd-templates", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--scheduler", help="dask.distributed scheduler address")
    parser.add_argument("--coadd-pixel-scale", type=float, default=0.2)
    parser.add_argument("--json", help="also write the results to this JSON file")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args()

    rows = args.rows.split(",")
    unknown = [row for row in rows if row not in ALL_ROWS]
    if unknown:
        parser.error(f"unknown rows {unknown}; known: {ALL_ROWS}")
    results = []
    for row in rows:
        method, mode = row.split("-", 1)
        result = validate_shear(
            mode,  # type: ignore[arg-type]
            n_objects=args.n_objects,
            snr=_snr(args.snr),
            seed=args.seed,
            workers=args.workers,
            scheduler=args.scheduler,
            coadd_pixel_scale=args.coadd_pixel_scale,
            progress=not args.quiet,
            method=method,  # type: ignore[arg-type]
            shape=args.shape if method == "metacal" else "admom",  # type: ignore[arg-type]
            bfd_templates=args.bfd_templates,
        )
        results.append(result)
    print(table(results))
    print()
    for result in results:
        per_pair = result["cpu_seconds"] / result["n_objects"]
        # sigma(m1) scales as 1 / sqrt(N): pairs and CPU for the paper's precision
        needed = result["n_objects"] * (result["m1_err"] / PAPER_SIGMA_M) ** 2
        print(
            f"{result['method']} {result['mode']}: {result['n_objects']} pairs, "
            f"{result['n_used']} used, wall {result['wall_seconds']:.0f} s, "
            f"CPU {result['cpu_seconds']:.0f} s ({per_pair:.2f} s/pair); "
            f"sigma_m = {PAPER_SIGMA_M:g} needs ~{needed:.2g} pairs, "
            f"~{needed * per_pair / 3600.0:.3g} CPU hours"
            + ("" if math.isfinite(needed) else " (no estimate)")
        )
    if args.json:
        with open(args.json, "w") as stream:
            json.dump(results, stream, indent=2, default=float)


if __name__ == "__main__":
    main()
