"""``cellcoadd build`` serially and on a local process pool: wall, CPU, main-process peak RSS.

The job is :mod:`bench_peers`' realistic one: an LSST-sized patch (``--cells-per-patch``
inner cells per side plus the border ring: 484 cells of 150 px inner + 2 x 50 px border
at 0.2 arcsec/px by default) from ``--exposures`` FITS exposure files of ``--size`` px at
0.26 arcsec/px, each covering the patch. The inputs are written once into ``--workdir``
(kept there: later runs reuse them).

Each build is the command in a fresh process (``cellcoadd build ... --workers N``),
which reports from inside itself, once the command is done (its pool shut down, its
workers reaped): its own CPU s and those of its children (the workers), its own peak RSS
(``ru_maxrss`` of the main process only, not of the workers) and its wall time. Rounds
interleave the worker counts, so load drifts hit all; medians are printed, with the load
average (on a shared machine, CPU seconds are the robust figure: wall time depends on
what else runs).

Run as ``.venv/bin/python benchmarks/bench_pool.py --workdir /tmp/pool-inputs
[--rounds N] [--workers 1,2] [--format h5|fits] [--n-noise K]``; ``--cells-per-patch 4
--size 1400`` for a quick check.
"""

from __future__ import annotations

import os

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from common import format_table, machine_summary  # noqa: E402

#: Runs the command in this (fresh) process and appends its own measurements to a file.
CHILD = """
import json, resource, sys, time
start = time.perf_counter()
from cellcoadd.cli.main import main
args, report = json.loads(sys.argv[1])
try:
    main(args)
except SystemExit as exit_:
    if exit_.code:
        raise
me = resource.getrusage(resource.RUSAGE_SELF)
children = resource.getrusage(resource.RUSAGE_CHILDREN)
with open(report, "w") as out:
    json.dump({
        "wall": time.perf_counter() - start,
        "cpu_main": me.ru_utime + me.ru_stime,
        "cpu_workers": children.ru_utime + children.ru_stime,
        "rss_main_mb": me.ru_maxrss / 1024,
    }, out)
"""


def write_inputs(work: Path, cells_per_patch: int, n_exposures: int, size: int) -> list[str]:
    """The realistic job's exposure files and sky map in ``work`` (made if missing)."""
    from bench_peers import CENTER, PIXEL_SCALE, grid_wcs, make_exposures

    from cellcoadd.geometry import SkyMap, SkyMapConfig
    from cellcoadd.io.exposures.exposure_io import write_exposure

    config = SkyMapConfig(
        pixel_scale=PIXEL_SCALE,
        cell_inner=150,
        cell_border=50,
        cells_per_patch=cells_per_patch,
        patches_per_tract=3,
    )
    skymap = SkyMap.from_centers([CENTER], config)
    paths = [work / f"visit{visit:04d}.fits" for visit in range(n_exposures)]
    stamp = work / "inputs.json"
    wanted = {"cells_per_patch": cells_per_patch, "exposures": n_exposures, "size": size}
    if stamp.exists() and json.loads(stamp.read_text()) == wanted:
        return [str(path) for path in paths]
    work.mkdir(parents=True, exist_ok=True)
    wcs, shape = grid_wcs(skymap[0].patch(1, 1))
    ra, dec = wcs.wcs_pix2world([[(shape[1] - 1) / 2, (shape[0] - 1) / 2]], 0)[0]
    exposures = make_exposures(
        (float(ra), float(dec)), n_exposures, size, max_rotation=10.0, max_offset=10.0
    )
    for exposure, path in zip(exposures, paths, strict=True):
        write_exposure(exposure, path, overwrite=True)
    (work / "skymap.json").write_text(skymap.to_json())
    stamp.write_text(json.dumps(wanted))
    return [str(path) for path in paths]


def run_build(paths: list[str], work: Path, workers: int, out: Path, n_noise: int) -> dict:
    """One ``cellcoadd build`` in a fresh process: its own report (see :data:`CHILD`)."""
    args = ["build", *paths, "--skymap", str(work / "skymap.json"), "--tract", "0"]
    args += ["--patch", "1,1", "--n-noise", str(n_noise), "--workers", str(workers)]
    args += ["--out", str(out), "--overwrite", "--quiet"]
    with tempfile.NamedTemporaryFile(suffix=".json") as report:
        start = time.perf_counter()
        subprocess.run(
            [sys.executable, "-c", CHILD, json.dumps([args, report.name])],
            check=True,
            capture_output=True,
        )
        wall = time.perf_counter() - start
        result = json.loads(Path(report.name).read_text())
    result["wall_process"] = wall
    result["load"] = os.getloadavg()[0]
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", required=True, help="inputs go (and stay) here")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--workers", default="1,2", help="comma-separated pool sizes")
    parser.add_argument("--format", choices=["h5", "fits"], default="h5")
    parser.add_argument("--n-noise", type=int, default=3)
    parser.add_argument("--cells-per-patch", type=int, default=20)
    parser.add_argument("--exposures", type=int, default=6)
    parser.add_argument("--size", type=int, default=3800, help="exposure side, px")
    parser.add_argument("--json", help="write every run's figures here")
    args = parser.parse_args()
    work = Path(args.workdir)
    start = time.perf_counter()
    paths = write_inputs(work, args.cells_per_patch, args.exposures, args.size)
    megabytes = sum(os.path.getsize(path) for path in paths) / 1e6
    print(f"pool: {machine_summary()}")
    print(
        f"{len(paths)} exposure files of {args.size} px ({megabytes:.0f} MB), "
        f"{args.cells_per_patch} + 2 cells per patch side, K = {args.n_noise}, "
        f".{args.format} output; inputs ready in {time.perf_counter() - start:.1f} s\n"
    )
    counts = [int(n) for n in args.workers.split(",")]
    runs: dict[int, list[dict]] = {n: [] for n in counts}
    out = work / f"coadd.{args.format}"
    for number in range(args.rounds):
        for n in counts:
            result = run_build(paths, work, n, out, args.n_noise)
            runs[n].append(result)
            print(f"round {number + 1}, workers {n}: {json.dumps(result)}", flush=True)
    print()
    rows = []
    for n in counts:

        def median(key: str, n: int = n) -> float:
            return float(np.median([run[key] for run in runs[n]]))

        cpu = [run["cpu_main"] + run["cpu_workers"] for run in runs[n]]
        rows.append(
            (
                n,
                median("wall"),
                float(np.median(cpu)),
                median("cpu_main"),
                median("cpu_workers"),
                median("rss_main_mb"),
                median("load"),
            )
        )
    print(
        format_table(
            ["workers", "wall s", "CPU s", "main CPU s", "workers CPU s", "main RSS MB", "load"],
            rows,
            ["d", ".1f", ".1f", ".1f", ".1f", ".0f", ".1f"],
        )
    )
    serial = rows[0]
    for row in rows[1:]:
        print(
            f"\nworkers {row[0]} vs {serial[0]}: wall {serial[1] / row[1]:.2f}x faster, "
            f"CPU {100 * (row[2] / serial[2] - 1):+.0f}%, main RSS {row[5]:.0f} MB "
            f"(vs {serial[5]:.0f} MB)"
        )
    if args.json:
        Path(args.json).write_text(json.dumps({str(n): runs[n] for n in counts}, indent=1))


if __name__ == "__main__":
    main()
