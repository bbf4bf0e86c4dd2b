"""Cost of ``build_cell`` against the number of input exposures, on one core.

The job: one 250 x 250 cell with the LSST defaults (0.2 arcsec/px, inner 150, border 50)
coadded from N noise-only exposures at 0.26 arcsec/px (360 x 360 px, random rotation
and offset, Moffat PSF, see :func:`common.covering_exposures`) with K = 3 noise
realizations and a 35 px PSF stamp.

Each N runs in a fresh process (one numba thread, one BLAS thread) so memory figures do
not mix: after a warm-up build, the median wall and CPU time of repeated builds, and the
peak of the memory allocated *during* a build (``tracemalloc``: numpy arrays included;
the exposures themselves, allocated before, are not counted). Streaming accumulation
should keep that peak flat in N. ``--profile`` adds the share of each build stage at
N = 100 (cProfile, cumulative time).

Run as ``.venv/bin/python benchmarks/bench_build_cell.py [--repeats N] [--profile]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

from common import covering_exposures, format_table, lsst_skymap, machine_summary

N_EXPOSURES = (10, 50, 100, 200)
CELL_INDEX = (50, 50)  # a cell in the middle of the tract
# Stages of a build and the functions whose cumulative time they are (cProfile names).
STAGES = {
    "select + map": "select_exposure",
    "input planes + noise": "input_planes",
    "warp": "accumulate_warped",
    "mask": "warp_mask_or",
    "PSF": "coadd_psf_contribution",
    "PSF moments": "psf_moments",
}


def measure_one(n_exposures: int, repeats: int, seed: int) -> dict[str, float]:
    """Time and peak memory of building the benchmark cell from ``n_exposures`` inputs."""
    import numba

    from cellcoadd.builder.cell import build_cell
    from cellcoadd.model.build_config import BuildConfig

    numba.set_num_threads(1)
    cell = lsst_skymap()[0].cell(*CELL_INDEX)
    config = BuildConfig(n_noise=3, psf_size=35)
    start = time.perf_counter()
    exposures = covering_exposures(cell, n_exposures, seed)
    generation = time.perf_counter() - start
    build_cell(cell, exposures[:2], config, seed)  # warm-up: imports, numba cache loads
    walls, cpus = [], []
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        coadd = build_cell(cell, exposures, config, seed)
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    build_cell(cell, exposures, config, seed)
    peak = tracemalloc.get_traced_memory()[1] - before
    tracemalloc.stop()
    return {
        "n": n_exposures,
        "used": coadd.n_used,
        "wall": sorted(walls)[len(walls) // 2],
        "cpu": sorted(cpus)[len(cpus) // 2],
        "peak_mb": peak / 1e6,
        "generation": generation,
    }


def profile_stages(n_exposures: int, seed: int) -> dict[str, float]:
    """Share of the build time spent in each stage (cumulative cProfile time)."""
    import cProfile
    import pstats

    import numba

    from cellcoadd.builder.cell import build_cell

    numba.set_num_threads(1)
    cell = lsst_skymap()[0].cell(*CELL_INDEX)
    exposures = covering_exposures(cell, n_exposures, seed)
    build_cell(cell, exposures[:2], seed=seed)
    profiler = cProfile.Profile()
    profiler.enable()
    build_cell(cell, exposures, seed=seed)
    profiler.disable()
    stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
    cumulative = {}
    total = 0.0
    for (_, _, name), (_, _, _, cum, _) in stats.items():
        if name == "build_cell":
            total = cum
        for stage, function in STAGES.items():
            if name == function:
                cumulative[stage] = cumulative.get(stage, 0.0) + cum
    shares = {stage: cumulative.get(stage, 0.0) / total for stage in STAGES}
    shares["total_s"] = total
    return shares


def run_child(arguments: list[str]) -> dict:
    """Run this script in a fresh single-threaded process and return its JSON answer."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env["NUMBA_NUM_THREADS"] = "1"
    answer = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), *arguments],
        env=env,
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(answer.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--profile", action="store_true", help="stage shares at N = 100")
    parser.add_argument("--child", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--child-profile", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        print(json.dumps(measure_one(args.child, args.repeats, args.seed)))
        return
    if args.child_profile is not None:
        print(json.dumps(profile_stages(args.child_profile, args.seed)))
        return

    print(f"build_cell: 250x250 cell, K=3, PSF 35; {machine_summary()}")
    print(f"one process per N, 1 thread; times: median of {args.repeats} builds\n")
    results = [
        run_child(["--child", str(n), "--repeats", str(args.repeats), "--seed", str(args.seed)])
        for n in N_EXPOSURES
    ]
    reference = results[0]
    rows = [
        (
            r["n"],
            r["used"],
            r["wall"],
            r["cpu"],
            1e3 * r["wall"] / r["n"],
            (r["wall"] / r["n"]) / (reference["wall"] / reference["n"]),
            r["peak_mb"],
            r["peak_mb"] / reference["peak_mb"],
        )
        for r in results
    ]
    header = [
        "N", "used", "wall s", "CPU s", "ms/exposure", "per exposure / N=10", "peak MB",
        "peak / N=10",
    ]  # fmt: skip
    print(format_table(header, rows, ["d", "d", ".3f", ".3f", ".2f", ".2f", ".1f", ".2f"]))
    at_100 = next(r for r in results if r["n"] == 100)
    print(f"\ntarget <= 1 s at N = 100: {at_100['wall']:.2f} s")
    if args.profile:
        shares = run_child(["--child-profile", "100", "--seed", str(args.seed)])
        total = shares.pop("total_s")
        print(f"\nstage shares at N = 100 (cProfile, {total:.2f} s with profiling overhead)\n")
        stage_rows = [(stage, 100 * share) for stage, share in shares.items()]
        stage_rows.append(("other", 100 * (1 - sum(shares.values()))))
        print(format_table(["stage", "% of build"], stage_rows, ["s", ".1f"]))


if __name__ == "__main__":
    main()
