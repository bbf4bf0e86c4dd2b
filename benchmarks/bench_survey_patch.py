"""A patch from hundreds of exposure files: memory per process, outputs, parallel speed.

The job: ``--exposures`` (default 50 and 200) noise-only exposure files of ``--ccd`` x
``--ccd`` px (default 900) at 0.2 arcsec/px, each covering the whole patch (a deep stack
with small dithers and rotations), written once with cellcoadd's exposure writer; a patch
of 2 x 2 inner cells plus its border (16 cells of 250 x 250 px), K = 3. The inputs are
given to ``build_patch`` as exposure *sources* (:class:`cellcoadd.io.ExposureFile`):
overlap is decided from the headers, and each worker loads one exposure cut to one block
of cells at a time.

Every run happens in a fresh Python process, so its peak resident memory (``ru_maxrss``
of the process, and of its worker processes) belongs to that run alone. For each number
of exposures: serial, the process pool of 2 workers, and (``--dask``) a dask
``LocalCluster`` of 2 single-threaded workers. Printed per run: wall and CPU seconds
(process + workers), peak RSS of the main process and of the largest worker, and the
SHA-256 of the written coadd (HDF5): equal hashes mean bit-identical outputs. Then the
ratios: peak RSS at the largest over the smallest number of exposures (target: within
20%), and the pool's speed-up over the serial run of the same size (target: within 10% of
2x). ``--repeats`` interleaves rounds and reports medians. With each row: how many cores
were idle in the second before the run (from ``/proc/stat``) and the load average after.

Run as ``.venv/bin/python benchmarks/bench_survey_patch.py [--exposures 50,200] [--dask]``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from common import format_table, idle_cores, machine_summary

SKY_CENTER = (60.0, -30.0)
PIXEL_SCALE = 0.2
SKY = dict(pixel_scale=PIXEL_SCALE, cell_inner=150, cell_border=50)


def _patch(cells_per_patch: int = 2):
    from cellcoadd import SkyMap, SkyMapConfig

    config = SkyMapConfig(**SKY, cells_per_patch=cells_per_patch)
    tract = SkyMap.from_centers([SKY_CENTER], config)[0]
    return tract.patch(tract.n_patches[0] // 2, tract.n_patches[1] // 2)


def write_inputs(directory: Path, n: int, ccd: int, cells_per_patch: int = 2) -> list[Path]:
    """``n`` noise-only exposure files covering the benchmark patch (reused if present)."""
    import galsim
    from common import exposure_wcs

    from cellcoadd import Exposure, write_exposure

    patch = _patch(cells_per_patch)
    box = patch.outer_bbox
    ra, dec = patch.tract.pixel_to_sky(
        [(box.x_start + box.x_stop - 1) / 2], [(box.y_start + box.y_stop - 1) / 2]
    )
    rng = np.random.default_rng(7)
    paths = []
    psf = galsim.Moffat(beta=3.5, fwhm=0.8)
    for visit in range(n):
        path = directory / f"visit{visit:04d}.fits"
        paths.append(path)
        if path.exists():
            continue
        offset = rng.uniform(-5.0, 5.0, size=2) / 3600.0
        wcs = exposure_wcs(
            (float(ra[0]) + offset[0], float(dec[0]) + offset[1]),
            (ccd, ccd),
            PIXEL_SCALE,
            rotation_deg=float(rng.uniform(0, 360)),
        )
        image = rng.normal(0.0, 3.0, size=(ccd, ccd)).astype(np.float32)
        exposure = Exposure(
            image=image,
            wcs=wcs,
            variance=9.0,
            psf=psf,
            visit=visit,
            detector=0,
            band="r",
            zero_point=30.0,
        )
        write_exposure(exposure, path)
    return paths


def run_one(paths: list[str], executor: str, out: str, cells_per_patch: int = 2) -> dict:
    """One build in this (fresh) process; the measurements of that run."""
    from cellcoadd import BuildConfig, ExposureFile, build_patch, write

    start_wall, start_cpu = time.perf_counter(), time.process_time()
    sources = [ExposureFile(p) for p in paths]
    config = BuildConfig(n_noise=3, psf_size=35)
    if executor == "dask":
        import dask
        from distributed import Client, LocalCluster

        malloc = {"distributed.nanny.pre-spawn-environ.MALLOC_MMAP_THRESHOLD_": 33554432}
        with (
            dask.config.set(malloc),
            LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as cluster,
            Client(cluster) as client,
        ):
            coadd = build_patch(
                _patch(cells_per_patch), sources, config, seed=1, progress=False, scheduler=client
            )
    else:
        workers = 2 if executor == "pool" else 1
        coadd = build_patch(
            _patch(cells_per_patch), sources, config, seed=1, progress=False, workers=workers
        )
    write(coadd, out, overwrite=True)
    wall = time.perf_counter() - start_wall
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {
        "wall": wall,
        "cpu": time.process_time() - start_cpu + children.ru_utime + children.ru_stime,
        "rss_main_mb": own.ru_maxrss / 1024,
        "rss_worker_mb": children.ru_maxrss / 1024,
        "sha256": hashlib.sha256(Path(out).read_bytes()).hexdigest(),
        "load": os.getloadavg()[0],
        "used": int(sum(c.n_used for c in coadd.cells.values())),
    }


def measure(paths: list[Path], executor: str, workdir: Path, cells_per_patch: int) -> dict:
    """:func:`run_one` in a fresh interpreter."""
    out = workdir / f"coadd-{executor}-{len(paths)}.h5"
    idle = idle_cores(1.0)
    arguments = ([str(p) for p in paths], executor, str(out), cells_per_patch)
    code = (
        f"import json, sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); "
        f"import bench_survey_patch as b; print(json.dumps(b.run_one(*{arguments!r})))"
    )
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, check=False
    )
    if result.returncode != 0:
        raise RuntimeError(f"{executor} run failed:\n{result.stderr[-3000:]}")
    return {**json.loads(result.stdout.strip().splitlines()[-1]), "idle": idle}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--exposures", default="50,200", help="numbers of exposure files")
    parser.add_argument("--ccd", type=int, default=900, help="exposure side, px")
    parser.add_argument("--repeats", type=int, default=1, help="interleaved rounds")
    parser.add_argument("--dask", action="store_true", help="also run on a dask LocalCluster")
    parser.add_argument("--workdir", help="keep the exposure files here (default: temporary)")
    parser.add_argument(
        "--cells-per-patch",
        type=int,
        default=2,
        help="inner cells per patch side (2: 16 cells with the border ring; the exposures "
        "must cover the patch: 6 needs --ccd 1600)",
    )
    args = parser.parse_args()
    n_cells = len(_patch(args.cells_per_patch).cells)
    counts = [int(n) for n in args.exposures.split(",")]
    executors = ["serial", "pool"] + (["dask"] if args.dask else [])
    print(f"machine: {machine_summary()}")
    print(
        f"job: patch of {n_cells} cells (250 x 250 px, K = 3) from {counts} exposure files of "
        f"{args.ccd} x {args.ccd} px, each covering the patch; inputs as ExposureFile sources"
    )
    with tempfile.TemporaryDirectory() as temporary:
        workdir = Path(args.workdir or temporary)
        workdir.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        paths = write_inputs(workdir, max(counts), args.ccd, args.cells_per_patch)
        print(f"inputs: {max(counts)} files written in {time.perf_counter() - start:.1f} s")
        runs: dict[tuple[int, str], list[dict]] = {}
        for _ in range(args.repeats):
            for n in counts:
                for executor in executors:
                    runs.setdefault((n, executor), []).append(
                        measure(paths[:n], executor, workdir, args.cells_per_patch)
                    )
    rows = []
    summary: dict[tuple[int, str], dict] = {}
    for (n, executor), results in runs.items():
        median = {k: float(np.median([r[k] for r in results])) for k in ("wall", "cpu")}
        last = results[-1]
        summary[(n, executor)] = {**last, **median}
        rows.append(
            [
                n,
                executor,
                median["wall"],
                median["cpu"],
                last["rss_main_mb"],
                last["rss_worker_mb"],
                last["used"],
                last["sha256"][:12],
                last["idle"],
                last["load"],
            ]
        )
    print()
    print(
        format_table(
            ["exposures", "run", "wall s", "CPU s", "RSS main MB", "RSS worker MB", "inputs used"]
            + ["coadd sha256", "idle cores before", "load 1 min"],
            rows,
            ["d", "s", ".1f", ".1f", ".0f", ".0f", "d", "s", ".2f", ".2f"],
        )
    )
    print()
    lo, hi = min(counts), max(counts)
    for n in counts:
        hashes = {summary[(n, e)]["sha256"] for e in executors}
        same = "identical" if len(hashes) == 1 else "DIFFERENT"
        print(f"{n} exposures: outputs of {', '.join(executors)} are {same}")
    ratio_rows = []
    for executor in executors:
        main_ratio = summary[(hi, executor)]["rss_main_mb"] / summary[(lo, executor)]["rss_main_mb"]
        worker = summary[(lo, executor)]["rss_worker_mb"]
        worker_ratio = summary[(hi, executor)]["rss_worker_mb"] / worker if worker else float("nan")
        ratio_rows.append([executor, main_ratio, worker_ratio])
    print()
    print(f"peak RSS at {hi} over {lo} exposures (target <= 1.20):")
    print(format_table(["run", "main", "worker"], ratio_rows, ["s", ".2f", ".2f"]))
    print()
    for n in counts:
        serial = summary[(n, "serial")]
        pool = summary[(n, "pool")]
        print(
            f"{n} exposures: pool of 2 speed-up {serial['wall'] / pool['wall']:.2f}x "
            f"(target >= 1.8x), CPU pool / serial {pool['cpu'] / serial['cpu']:.2f}"
        )


if __name__ == "__main__":
    main()
