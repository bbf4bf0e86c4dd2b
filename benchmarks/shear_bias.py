"""Shear bias of metacal, BFD and AnaCal on cell coadds vs multi-epoch, in Table 1's layout.

Runs :func:`cellcoadd.pipelines.validate_shear` for the rows of the paper's Table 1
(metacal coadd, metacal multi-epoch, BFD coadd, BFD multi-epoch) and AnaCal on coadds,
and prints m1 +- err beside the paper's, c1, c2, the pairs used and the CPU time ("-"
where the paper has no row), the settings each row ran with, then what a given precision
(``--target-sigma``, default the paper's 4e-4) would cost. ``single`` rows (the first
epoch alone, e.g. ``metacal-single``) can be added with ``--rows``.

Presets (:mod:`cellcoadd.pipelines.validation.bias_presets`): ``--preset none`` (default) runs every
row with the command line's S/N and ``--shear``; ``--preset high-snr`` runs S/N 10^4 with
what each row needs there (BFD: the targets as templates, no ring partners, g1 = 1e-3;
metacal and AnaCal: g1 = 0.02 and ring partners) and, unless ``--n-objects`` is given,
enough pairs per row for sigma_m <= 2e-4 (about 20 CPU minutes for the five rows).

The default run is small (200 pairs per row at S/N 10-50, about 15 CPU minutes): the error
on m1 is then ~0.1 (it falls as 1/sqrt(N)).

Usage::

    .venv/bin/python benchmarks/shear_bias.py                      # ~15 CPU min, 2 workers
    .venv/bin/python benchmarks/shear_bias.py --preset high-snr --json /tmp/high.json
    .venv/bin/python benchmarks/shear_bias.py --n-objects 2000 --json bias.json
    .venv/bin/python benchmarks/shear_bias.py --rows metacal-coadd --snr 10000 --n-objects 400
    .venv/bin/python benchmarks/shear_bias.py --rows bfd-coadd,bfd-multi-epoch --n-objects 300,100
    .venv/bin/python benchmarks/shear_bias.py --shape wmom --rows metacal-coadd,metacal-single \
        --target-sigma 5e-3,4e-4
    .venv/bin/python benchmarks/shear_bias.py --scheduler tcp://127.0.0.1:8786 --n-objects 100000 \\
        --checkpoint-dir runs/ --checkpoint-every 2000      # a killed run resumes from runs/
    .venv/bin/python benchmarks/shear_bias.py --rows metacal-coadd --shape wmom --compare-cuts

``--compare-cuts`` adds, for each metacal row, ``m1`` without cuts, with each cut alone and
with both, and each one's paired difference from no cuts (the same pairs and jackknife
blocks): whether a cut biases ``m1``, and what it costs in per-pair scatter.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from typing import Any

from cellcoadd.pipelines import validate_shear
from cellcoadd.pipelines.validation.bias_presets import (
    HIGH_SNR_PAIRS,
    PRESETS,
    describe_settings,
    row_settings,
)
from cellcoadd.pipelines.validation.bias_table import PAPER_TABLE1_ROWS, format_cut_comparison

#: sigma(m1) of the paper's metacal rows.
PAPER_SIGMA_M = 4.0e-4
#: Default rows: the paper's Table 1 and AnaCal on coadds.
ROWS = ("metacal-coadd", "metacal-multi-epoch", "bfd-coadd", "bfd-multi-epoch", "anacal-coadd")
#: Rows that can be asked for with --rows.
ALL_ROWS = (*ROWS, "metacal-single", "bfd-single", "anacal-single")
_NAMES = {"metacal": "metacal", "bfd": "BFD", "anacal": "AnaCal"}
#: Pairs per row without a preset.
DEFAULT_PAIRS = 200


def _snr(text: str) -> float | tuple[float, float] | None:
    if text == "none":
        return None
    values = [float(part) for part in text.split(",")]
    return values[0] if len(values) == 1 else (values[0], values[1])


def _pm(value: float, error: float, digits: int) -> str:
    return f"{value:+.{digits}f} +- {error:.{digits}f}"


def table(results: list[dict[str, Any]]) -> str:
    """Table 1's layout: one line per row, ours beside the paper's m1."""
    errors = [r["m1_err"] for r in results if math.isfinite(r["m1_err"])]
    digits = 5 if errors and min(errors) < 1e-3 else 4
    width = 2 * digits + 10
    header = (
        f"{'sample':<20} {'g1':>6} {'m1 (ours)':>{width}} {'m1 (paper)':>{width}} "
        f"{'c1':>{width}} {'c2':>{width}} {'pairs used/N':>13} {'CPU s':>8}"
    )
    lines = [header, "-" * len(header)]
    for r in results:
        method, mode = r["method"], r["mode"]
        paper = PAPER_TABLE1_ROWS.get((method, mode))
        paper_text = "-" if paper is None else _pm(paper[0], paper[1], digits)
        name = f"{_NAMES[method]} {mode}"
        g1 = r["settings"]["sim"]["shear"][0]
        used = f"{r['n_used']}/{r['n_objects']}"
        lines.append(
            f"{name:<20} {g1:>6g} {_pm(r['m1'], r['m1_err'], digits):>{width}} "
            f"{paper_text:>{width}} {_pm(r['c1'], r['c1_err'], digits):>{width}} "
            f"{_pm(r['c2'], r['c2_err'], digits):>{width}} {used:>13} "
            f"{r['cpu_seconds']:>8.0f}"
        )
    lines.append("'single': the first epoch alone (not in the paper); requirement |m1| < 0.001")
    return "\n".join(lines)


def cost_lines(results: list[dict[str, Any]], targets: list[float], workers: int) -> list[str]:
    """Per row: pairs, CPU; and the pairs and CPU hours each target sigma_m would take
    (sigma_m falls as 1 / sqrt(N); CPU grows as N, the prior of BFD aside)."""
    lines = []
    for r in results:
        per_pair = r["cpu_seconds"] / r["n_objects"]
        head = (
            f"{_NAMES[r['method']]} {r['mode']}: {r['n_objects']} pairs, {r['n_used']} used, "
            f"sigma_m = {r['m1_err']:.2g}, wall {r['wall_seconds']:.0f} s, "
            f"CPU {r['cpu_seconds']:.0f} s ({per_pair:.2f} s/pair)"
        )
        parts = []
        for target in targets:
            needed = r["n_objects"] * (r["m1_err"] / target) ** 2
            if not math.isfinite(needed):
                parts.append(f"sigma_m = {target:g}: no estimate")
                continue
            hours = needed * per_pair / 3600.0
            parts.append(
                f"sigma_m = {target:g} needs ~{needed:.2g} pairs, ~{hours:.3g} CPU h "
                f"(~{hours / workers:.3g} h on {workers} workers)"
            )
        lines.append(head + "; " + "; ".join(parts))
    return lines


def _pairs(text: str | None, rows: list[str], preset: str) -> list[int]:
    if text is None:
        if preset == "high-snr":
            return [HIGH_SNR_PAIRS[row] for row in rows]
        return [DEFAULT_PAIRS] * len(rows)
    values = [int(part) for part in text.split(",")]
    if len(values) == 1:
        return values * len(rows)
    if len(values) != len(rows):
        raise ValueError(f"--n-objects gives {len(values)} values for {len(rows)} rows")
    return values


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--n-objects",
        help=f"pairs per row: N, or one per row N1,N2,... (default {DEFAULT_PAIRS}; "
        "high-snr: sized per row for sigma_m <= 2e-4)",
    )
    parser.add_argument("--snr", default="10,50", help="LO,HI, VALUE or 'none' (sim noise)")
    parser.add_argument("--shear", type=float, help="input g1 (default 0.02; high-snr BFD: 1e-3)")
    parser.add_argument("--preset", default="none", choices=PRESETS)
    parser.add_argument("--rows", default=",".join(ROWS), help=f"comma-separated of {ALL_ROWS}")
    parser.add_argument("--shape", default="admom", choices=("admom", "wmom"))
    parser.add_argument(
        "--bfd-templates", type=int, help="independent BFD templates (default: from the S/N)"
    )
    parser.add_argument(
        "--object-offset", type=float,
        help="coadd rows: random object positions within this many coadd pixels of the "
        "cell centre (default: 5 with --preset high-snr, else 0)",
    )  # fmt: skip
    parser.add_argument("--no-rotated-partners", action="store_true")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--scheduler", help="dask.distributed scheduler address")
    parser.add_argument("--coadd-pixel-scale", type=float, default=0.2)
    parser.add_argument(
        "--target-sigma", default=str(PAPER_SIGMA_M), help="sigma_m values to cost, comma-separated"
    )
    parser.add_argument(
        "--checkpoint-dir",
        help="save each row's pairs to <dir>/<row>-seed<seed>.npz as they finish; a rerun "
        "resumes from there (--checkpoint-every pairs between saves)",
    )
    parser.add_argument("--checkpoint-every", type=int, default=1000)
    parser.add_argument(
        "--compare-cuts",
        action="store_true",
        help="metacal rows: m1 without cuts, with each cut alone and with both",
    )
    parser.add_argument("--json", help="also write the results to this JSON file")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args()

    rows = args.rows.split(",")
    unknown = [row for row in rows if row not in ALL_ROWS]
    if unknown:
        parser.error(f"unknown rows {unknown}; known: {ALL_ROWS}")
    try:
        pairs = _pairs(args.n_objects, rows, args.preset)
    except ValueError as exc:
        parser.error(str(exc))
    results, described = [], []
    for row, n_objects in zip(rows, pairs, strict=True):
        options = row_settings(
            row,
            args.preset,
            snr=_snr(args.snr),
            shear=args.shear,
            rotated_partners=not args.no_rotated_partners,
            shape=args.shape,
            object_offset=args.object_offset,
        )
        if options["method"] == "bfd" and args.bfd_templates is not None:
            options["bfd_templates"] = args.bfd_templates
        described.append(f"{row}: {n_objects} pairs, {describe_settings(options)}")
        print(described[-1], flush=True)
        checkpoint = None
        if args.checkpoint_dir:
            os.makedirs(args.checkpoint_dir, exist_ok=True)
            checkpoint = os.path.join(args.checkpoint_dir, f"{row}-seed{args.seed}.npz")
        result = validate_shear(
            n_objects=n_objects,
            seed=args.seed,
            workers=args.workers,
            scheduler=args.scheduler,
            checkpoint=checkpoint,
            checkpoint_every=args.checkpoint_every,
            coadd_pixel_scale=args.coadd_pixel_scale,
            progress=not args.quiet,
            compare_cuts=args.compare_cuts and options["method"] == "metacal",
            **options,
        )
        results.append(result)
    print()
    print(table(results))
    print()
    print(f"settings (preset {args.preset}, seed {args.seed}):")
    for line in described:
        print(f"  {line}")
    print()
    targets = [float(part) for part in args.target_sigma.split(",")]
    for line in cost_lines(results, targets, args.workers):
        print(line)
    for result in results:
        if "cut_comparison" in result:
            print()
            print(format_cut_comparison(result))
    if args.json:
        with open(args.json, "w") as stream:
            json.dump(results, stream, indent=2, default=float)


if __name__ == "__main__":
    main()
