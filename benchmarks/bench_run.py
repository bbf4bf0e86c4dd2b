"""Tract runs at small scale: serial vs a LocalCluster vs a scheduler address, the exposure
index, and the cost of the bookkeeping.

The job: a tract of ``--patches`` x ``--patches`` patches (default 3 x 3) of
``--cells`` x ``--cells`` inner cells (default 4 x 4; 150 + 2 x 50 px at 0.2"/px, 36
cells per patch with the border ring, K = 3), from ``--visits`` x (patches) noise-only
exposure files (default 12 x 9 = 108 files) of ``--ccd`` x ``--ccd`` px (default: the
patch's outer box plus 100 px, 1100 px for 4 x 4 cells), one detector centred on each
patch per visit (dithered, rotated), so that each covers its patch and each patch reads
its own detector and its neighbours'. ``--cells 2 --ccd 520`` is the small job of the
first measurements (fixed costs per worker then dominate a 2 s patch); ``--cells 20``
gives patches the size of an LSST patch (484 cells; 9.9 GB of inputs, and each run's 7.5
GB of patch files, removed once hashed, so that ~20 GB of disk suffice). The files
are indexed (``cellcoadd index``), then the whole tract is run with ``cellcoadd run``:

* ``serial``: ``--workers 1`` (in the run's own process);
* ``workers2``: ``--workers 2`` (a LocalCluster of 2 single-threaded processes started
  and stopped by the run: its start-up, imports and compilation are part of the run);
* ``scheduler``: ``--scheduler ADDRESS`` of a LocalCluster of 2 workers started once, in
  another process, and warmed by one patch before the rounds (as a long-lived cluster
  would be).

Each run is a fresh process in a fresh output directory; rounds interleave the three
(``--repeats``) and every run is printed (the host's speed drifts between rounds by up
to ~10% here), then the medians. CPU is the run process and its children
(``RUSAGE_CHILDREN``), plus, for ``scheduler``, the CPU its workers used during the run
(psutil). Printed: wall, CPU, the ratios to serial, the CPU the patch tasks themselves
report (telling the cost of running two at once apart from start-up and scheduling),
SHA-256 of every patch (identical across modes), the peak RSS of the workers for 1 and
for all patches, the scheduler's round trip per task (no-op tasks), the index build time
per 1,000 files and the query time of a patch at 100,000 synthetic rows. The load
average and idle cores are printed with every run: on a shared machine the ratios are
only as good as the cores that were free.

Run as ``.venv/bin/python benchmarks/bench_run.py [--visits 12] [--repeats 1] [--quick]``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from common import format_table, idle_cores, machine_summary

SKY_CENTER = (60.0, -30.0)


def _skymap(patches: int, cells: int):
    from cellcoadd import SkyMap, SkyMapConfig

    config = SkyMapConfig(
        pixel_scale=0.2, cell_inner=150, cell_border=50, cells_per_patch=cells,
        patches_per_tract=patches,
    )  # fmt: skip
    return SkyMap.from_centers([SKY_CENTER], config)


def write_inputs(directory: Path, visits: int, patches: int, cells: int, ccd: int) -> list[Path]:
    """One noise-only exposure file per (visit, patch), centred on the patch (reused when
    the directory has it already: name it by the job)."""
    import galsim
    from common import exposure_wcs

    from cellcoadd import Exposure, write_exposure

    tract = _skymap(patches, cells)[0]
    rng = np.random.default_rng(26)
    paths = []
    for visit in range(visits):
        for detector, patch in enumerate(tract.patches):
            path = directory / f"visit{visit:03d}-det{detector:02d}.fits"
            paths.append(path)
            box = patch.inner_bbox
            x = (box.x_start + box.x_stop - 1) / 2 + rng.uniform(-10, 10)
            y = (box.y_start + box.y_stop - 1) / 2 + rng.uniform(-10, 10)
            rotation = rng.uniform(-2.0, 2.0)
            if path.exists():
                continue
            (ra,), (dec,) = tract.pixel_to_sky(x, y)
            variance = rng.uniform(1.0, 2.0)
            exposure = Exposure(
                image=rng.normal(0.0, np.sqrt(variance), (ccd, ccd)).astype(np.float32),
                wcs=exposure_wcs((float(ra), float(dec)), (ccd, ccd), 0.2, rotation),
                variance=variance,
                psf=galsim.Moffat(beta=3.5, fwhm=0.9),
                visit=visit,
                detector=detector,
                band="r",
                zero_point=30.0,
            )
            write_exposure(exposure, path)
    return paths


def _cli(args: list[str]) -> tuple[float, float, str]:
    """Run ``cellcoadd ARGS`` in a fresh process (its ``--out-dir`` emptied first, so that
    every run builds everything): wall s, CPU s (it and its children)."""
    if "--out-dir" in args:
        shutil.rmtree(args[args.index("--out-dir") + 1], ignore_errors=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    result = subprocess.run(
        [sys.executable, "-m", "cellcoadd", *args], capture_output=True, text=True, env=env
    )
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if result.returncode != 0:
        raise RuntimeError(f"cellcoadd {' '.join(args)} failed:\n{result.stderr[-3000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, result.stdout


def _tree_cpu(pid: int) -> float:
    import psutil

    total = 0.0
    root = psutil.Process(pid)
    for process in [root, *root.children(recursive=True)]:
        try:
            times = process.cpu_times()
            total += times.user + times.system
        except psutil.NoSuchProcess:
            continue
    return total


_CLUSTER = """
import sys, dask, distributed
from cellcoadd.builder.executors import DASK_WORKER_CONFIG
dask.config.set(DASK_WORKER_CONFIG)  # as docs/survey-runs.md asks of a cluster
cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0")
print(cluster.scheduler_address, flush=True)
sys.stdin.read()
cluster.close()
"""


def start_cluster() -> tuple[subprocess.Popen, str]:
    """A LocalCluster of 2 workers in another process, and its scheduler address."""
    process = subprocess.Popen(
        [sys.executable, "-c", _CLUSTER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    assert process.stdout is not None
    return process, process.stdout.readline().strip()


def task_overhead(address: str, n: int = 200) -> float:
    """Scheduler round trip per task (s): ``n`` no-op tasks submitted and gathered."""
    import distributed

    with distributed.Client(address) as client:
        client.gather(client.map(_noop, range(20), pure=False))  # warm
        start = time.perf_counter()
        client.gather(client.map(_noop, range(n), pure=False))
        return (time.perf_counter() - start) / n


def _noop(i: int) -> int:
    return i


def _hashes(out: Path) -> dict[str, str]:
    return {
        p.name: hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted((out / "tract_0").glob("patch_*"))
    }


def _remove_patch_files(out: Path) -> None:
    """Remove a run's patch files once hashed (its ledger and report stay): the runs of an
    LSST-sized tract write 8 GB each."""
    shutil.rmtree(out / "tract_0", ignore_errors=True)


def _task_cpu(out: Path) -> float:
    """CPU s the patch tasks report (their processes' CPU while they ran): the rest of a
    run's CPU is start-up, planning, scheduling and bookkeeping."""
    report = json.loads((out / "report.json").read_text())
    return sum(p.get("cpu_s", 0.0) for p in report["patches"] if p["state"] == "done")


def _peak_worker_rss(out: Path) -> float:
    report = json.loads((out / "report.json").read_text())
    return max(p.get("peak_rss_mb", 0.0) for p in report["patches"] if p["state"] == "done")


def index_time(paths: list[Path], db: Path, workers: int) -> float:
    """Seconds to index ``paths`` from scratch with ``workers`` processes."""
    from cellcoadd.io.exposures.index import ExposureIndex, absolute_entry
    from cellcoadd.model.manifest import ManifestEntry

    db.unlink(missing_ok=True)
    entries = [absolute_entry(ManifestEntry(path=str(p)), ".") for p in paths]
    with ExposureIndex(db) as index:
        update = index.update(entries, workers=workers)
    assert len(update.added) == len(paths), update.bad
    return update.seconds


def query_time(db: Path, rows: int, queries: int = 300) -> tuple[float, float, float]:
    """Fill an index with ``rows`` synthetic LSST-detector footprints over a 12 x 12 deg
    field; median query time (s) of an LSST patch polygon, mean rows returned, fill time."""
    from cellcoadd.io.exposures.index import Described, ExposureIndex, FileStamp
    from cellcoadd.model.manifest import ManifestEntry

    db.unlink(missing_ok=True)
    rng = np.random.default_rng(1)
    half = 0.11  # an LSST detector: 4k x 4k px at 0.2"/px ~ 0.23 deg
    start = time.perf_counter()
    with ExposureIndex(db) as index:
        header = json.dumps({"visit": 0, "detector": 0, "band": "r", "shape": [4000, 4000],
                             "valid_box": [0, 4000, 0, 4000], "zero_point": 31.4})  # fmt: skip
        for row in range(rows):
            ra, dec = rng.uniform(-6, 6), rng.uniform(-36, -24)
            dra = half / np.cos(np.radians(dec))
            corners = np.array(
                [[ra - dra, dec - half], [ra + dra, dec - half], [ra + dra, dec + half],
                 [ra - dra, dec + half]]
            )  # fmt: skip
            corners[:, 0] %= 360.0
            path = f"/survey/visit{row // 189:06d}-det{row % 189:03d}.fits"
            item = Described(
                ManifestEntry(path=path, layout="lsst", psf=path + ".psf"),
                (FileStamp(path, 1, 1),), header.replace('"visit": 0', f'"visit": {row}'),
                corners,
            )  # fmt: skip
            index.store(item)
        index.commit()
        fill = time.perf_counter() - start
        durations, found = [], []
        side = 0.17  # an LSST patch, deg
        for _ in range(queries):
            ra, dec = rng.uniform(-5, 5) % 360.0, rng.uniform(-35, -25)
            dra = side / 2 / np.cos(np.radians(dec))
            polygon = np.array(
                [[ra - dra, dec - side / 2], [ra + dra, dec - side / 2],
                 [ra + dra, dec + side / 2], [ra - dra, dec + side / 2]]
            )  # fmt: skip
            t0 = time.perf_counter()
            found.append(len(index.query(polygon)))
            durations.append(time.perf_counter() - t0)
    return float(np.median(durations)), float(np.mean(found)), fill


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--visits", type=int, default=12, help="visits (files per patch)")
    parser.add_argument("--patches", type=int, default=3, help="patches per tract side")
    parser.add_argument("--cells", type=int, default=4, help="inner cells per patch side")
    parser.add_argument("--ccd", type=int, help="exposure side, px (default: covers a patch)")
    parser.add_argument("--repeats", type=int, default=1, help="interleaved rounds")
    parser.add_argument("--rows", type=int, default=100_000, help="synthetic index rows")
    parser.add_argument("--workdir", help="keep the exposure files here (default: temporary)")
    parser.add_argument("--quick", action="store_true", help="3 visits, 10,000 rows: a check")
    parser.add_argument("--query-only", action="store_true", help="only the index query")
    args = parser.parse_args()
    if args.query_only:
        with tempfile.TemporaryDirectory() as temporary:
            median, mean_found, fill = query_time(Path(temporary) / "synthetic.sqlite", args.rows)
        print(
            f"index query at {args.rows:,} rows: {1000 * median:.2f} ms median per LSST patch "
            f"(~{mean_found:.0f} candidate inputs returned; filling took {fill:.0f} s)"
        )
        return
    if args.quick:
        args.visits, args.rows, args.cells = 3, 10_000, 2
    if args.ccd is None:
        args.ccd = (args.cells + 2) * 150 + 2 * 50 + 100  # the patch's outer box + 100 px
    print(f"machine: {machine_summary()}")
    n_patches = args.patches**2
    print(
        f"job: tract of {args.patches} x {args.patches} patches of {(args.cells + 2) ** 2} "
        f"cells (250 x 250 px, K = 3) from {args.visits * n_patches} exposure files of "
        f"{args.ccd} x {args.ccd} px"
    )
    with tempfile.TemporaryDirectory() as temporary:
        work = Path(args.workdir or temporary)
        inputs = work / f"inputs-{args.patches}p-{args.cells}c-{args.ccd}px"
        inputs.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        paths = write_inputs(inputs, args.visits, args.patches, args.cells, args.ccd)
        print(f"inputs: {len(paths)} files ready in {time.perf_counter() - start:.1f} s")
        (work / "skymap.json").write_text(_skymap(args.patches, args.cells).to_json())
        db = work / "inputs.sqlite"
        index_rows = []
        for workers in (1, 2):
            idle = idle_cores(0.5)
            seconds = index_time(paths, db, workers)
            index_rows.append([workers, seconds, 1000 * seconds / len(paths), idle])
        print()
        print(format_table(
            ["index workers", "s", "s per 1,000 files", "idle cores before"], index_rows,
            ["d", ".2f", ".1f", ".2f"],
        ))  # fmt: skip
        base = ["run", "--index", str(db), "--skymap", str(work / "skymap.json"), "--tract", "0"]
        base += ["-q", "--no-figure"]
        cluster, address = start_cluster()
        try:
            overhead = task_overhead(address)
            # a long-lived cluster has imported and compiled already: one patch to warm it
            _cli([*base, "--out-dir", str(work / "warm-up"), "--scheduler", address, "--patch",
                  "0,0"])  # fmt: skip
            _remove_patch_files(work / "warm-up")
            results: dict[str, list[dict]] = {}
            for round_ in range(args.repeats):
                for mode, extra in (
                    ("serial", ["--workers", "1"]),
                    ("workers2", ["--workers", "2"]),
                    ("scheduler", ["--scheduler", address]),
                ):
                    out = work / f"out-{mode}-{round_}"
                    idle = idle_cores(0.5)
                    before = _tree_cpu(cluster.pid) if mode == "scheduler" else 0.0
                    wall, cpu, _ = _cli([*base, "--out-dir", str(out), *extra])
                    if mode == "scheduler":
                        cpu += _tree_cpu(cluster.pid) - before
                    results.setdefault(mode, []).append({
                        "wall": wall, "cpu": cpu, "tasks": _task_cpu(out),
                        "hashes": _hashes(out),
                        "rss": _peak_worker_rss(out), "idle": idle,
                        "load": os.getloadavg()[0],
                    })  # fmt: skip
                    _remove_patch_files(out)
            # peak RSS of a worker: one whole patch each (two patches on two workers: none
            # cut into parts), then every patch (fresh LocalClusters)
            one = work / "out-one"
            _cli([*base, "--out-dir", str(one), "--workers", "2", "--patch", "1,1", "--patch",
                  "0,1"])  # fmt: skip
            rss_one = _peak_worker_rss(one)
            _remove_patch_files(one)
        finally:
            assert cluster.stdin is not None
            cluster.stdin.close()
            cluster.wait(timeout=60)
        # every run, in the order run: the host's speed drifts between rounds
        print()
        print(format_table(
            ["round", "run", "wall s", "CPU s", "tasks' CPU s", "idle cores before",
             "load 1 min"],
            [[k, mode, r["wall"], r["cpu"], r["tasks"], r["idle"], r["load"]]
             for k in range(args.repeats) for mode, runs in results.items()
             for r in runs[k : k + 1]],
            ["d", "s", ".1f", ".1f", ".1f", ".2f", ".2f"],
        ))  # fmt: skip
        rows = []
        keys = ("wall", "cpu", "tasks")
        serial = {k: float(np.median([r[k] for r in results["serial"]])) for k in keys}
        for mode, runs in results.items():
            median = {k: float(np.median([r[k] for r in runs])) for k in keys}
            rows.append([
                mode, median["wall"], median["cpu"], serial["wall"] / median["wall"],
                median["cpu"] / serial["cpu"], median["tasks"] / serial["tasks"],
                runs[-1]["rss"],
            ])  # fmt: skip
        print()
        print(format_table(
            ["run (medians)", "wall s", "CPU s", "speed-up", "CPU / serial",
             "tasks' CPU / serial", "peak RSS worker MB"], rows,
            ["s", ".1f", ".1f", ".2f", ".2f", ".2f", ".0f"],
        ))  # fmt: skip
        hashes = [r["hashes"] for runs in results.values() for r in runs]
        same = all(h == hashes[0] for h in hashes) and len(hashes[0]) == n_patches
        print(
            f"\noutputs: {len(hashes[0])} patch files per run, "
            f"{'identical' if same else 'DIFFERENT'} across every run and mode"
        )
        print("targets: speed-up >= 1.8x and CPU / serial <= 1.10 for workers2 and scheduler")
        rss_all = float(np.median([r["rss"] for r in results["workers2"]]))
        print(
            f"peak RSS of a worker: {rss_one:.0f} MB for 1 patch each, {rss_all:.0f} MB for "
            f"{n_patches} patches (ratio {rss_all / rss_one:.2f}, target: flat)"
        )
        print(f"scheduler round trip per task: {1000 * overhead:.1f} ms (no-op tasks)")
        median, mean_found, fill = query_time(work / "synthetic.sqlite", args.rows)
        print(
            f"index query at {args.rows:,} rows: {1000 * median:.2f} ms median per LSST patch "
            f"(~{mean_found:.0f} candidate inputs returned; filling took {fill:.0f} s)"
        )


if __name__ == "__main__":
    main()
