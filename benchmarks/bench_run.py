"""Survey runs at small scale: serial vs LocalClusters of N workers vs a scheduler
address, over several tracts and bands; the exposure index, and the cost of the
bookkeeping.

The job: ``--tracts`` tracts side by side (default 1; a row in RA, centres one tract's
width apart less 5%, so that neighbours overlap slightly), each of ``--patches`` x
``--patches`` patches (default 3 x 3) of ``--cells`` x ``--cells`` inner cells (default
4 x 4; 150 + 2 x 50 px at 0.2"/px, 36 cells per patch with the border ring, K = 3), in
each band of ``--bands`` (default ``r``), from ``--visits`` noise-only exposure files
per patch and band (default 12: 108 files for the default job) of ``--ccd`` x ``--ccd``
px (default: the patch's outer box plus 100 px, 1100 px for 4 x 4 cells), one detector
centred on each patch of each tract per visit (dithered, rotated), so that each covers
its patch and each patch reads its own detector and its neighbours' (across a tract's
edge too). ``--tracts 2 --bands g,r`` gives 36 patches from 432 files. ``--cells 2
--ccd 520`` is the small job of the first measurements (fixed costs per worker then
dominate a 2 s patch); ``--cells 20`` gives patches the size of an LSST patch (484
cells; 9.9 GB of inputs per tract and band, and each run's 7.5 GB of patch files,
removed once hashed, so that ~20 GB of disk suffice). The files are indexed
(``cellcoadd index``), then the whole job is run with ``cellcoadd run`` (every band and
tract of the index; outputs ``DIR/<band>/tract_<T>/patch_<X>_<Y>.fits``):

* ``serial``: ``--workers 1`` (in the run's own process);
* ``workersN`` for each N of ``--workers`` (default ``2``; e.g. ``2,4,8``):
  ``--workers N`` (a LocalCluster of N single-threaded processes started and stopped
  by the run: its start-up, imports and compilation are part of the run);
* ``scheduler``: ``--scheduler ADDRESS`` of a LocalCluster of ``--scheduler-workers``
  workers (default 2) started once, in another process, and warmed by one patch before
  the rounds (as a long-lived cluster would be).

Each run is a fresh process in a fresh output directory; rounds interleave the modes
(``--repeats``) and every run is printed (the host's speed drifts between rounds by up
to ~10% here), then the medians. CPU is the run process and its children
(``RUSAGE_CHILDREN``), plus, for ``scheduler``, the CPU its workers used during the run
(psutil). Printed: wall, CPU, the ratios to serial, the CPU the patch tasks themselves
report in the tracts' reports (telling the cost of running several at once apart from
start-up and scheduling), the run's wall less the tasks' summed wall per worker (what
the workers did not spend in patch tasks: start-up, planning, bookkeeping, idling at the
end), SHA-256 of every patch (identical across modes), the peak RSS of the workers for
1 and for all patches, the client's serial seconds per tract (``cellcoadd run`` again on
the serial run's finished directory, where every patch is up to date: planning, ledger
and reports; all tracts, and tract 0 alone), the scheduler's round trip per task (no-op
tasks), the index build time per 1,000 files and the query time of a patch at 100,000
synthetic rows. The load average and idle cores are printed with every run: on a shared
machine the ratios are only as good as the cores that were free.

Run as ``.venv/bin/python benchmarks/bench_run.py [--tracts 2] [--bands g,r]
[--workers 2,4] [--repeats 1] [--quick]``.
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
#: neighbouring tracts' centres are this fraction of a tract's width apart
TRACT_STEP = 0.95


def _skymap(tracts: int, patches: int, cells: int):
    """``tracts`` tracts in a row along RA, centred on :data:`SKY_CENTER`."""
    from cellcoadd import SkyMap, SkyMapConfig

    config = SkyMapConfig(
        pixel_scale=0.2, cell_inner=150, cell_border=50, cells_per_patch=cells,
        patches_per_tract=patches,
    )  # fmt: skip
    width = patches * cells * 150 * 0.2 / 3600.0  # deg, a tract's box
    step = TRACT_STEP * width / np.cos(np.radians(SKY_CENTER[1]))
    centers = [
        (SKY_CENTER[0] + (t - (tracts - 1) / 2) * step, SKY_CENTER[1]) for t in range(tracts)
    ]
    return SkyMap.from_centers(centers, config)


def write_inputs(
    directory: Path, visits: int, tracts: int, bands: list[str], patches: int, cells: int,
    ccd: int,
) -> list[Path]:  # fmt: skip
    """One noise-only exposure file per (band, visit, tract, patch), centred on the patch
    (reused when the directory has it already: name it by the job). Band k's visits are
    numbered from 1000 k; detectors count the patches of every tract."""
    import galsim
    from common import exposure_wcs

    from cellcoadd import Exposure, write_exposure

    sky = _skymap(tracts, patches, cells)
    paths = []
    for k, band in enumerate(bands):
        for visit in range(visits):
            for tract in sky:
                for i, patch in enumerate(tract.patches):
                    detector = tract.id * len(tract.patches) + i
                    path = directory / f"{band}-visit{1000 * k + visit:04d}-det{detector:03d}.fits"
                    paths.append(path)
                    if path.exists():
                        continue
                    rng = np.random.default_rng((26, k, visit, detector))
                    box = patch.inner_bbox
                    x = (box.x_start + box.x_stop - 1) / 2 + rng.uniform(-10, 10)
                    y = (box.y_start + box.y_stop - 1) / 2 + rng.uniform(-10, 10)
                    rotation = rng.uniform(-2.0, 2.0)
                    (ra,), (dec,) = tract.pixel_to_sky(x, y)
                    variance = rng.uniform(1.0, 2.0)
                    exposure = Exposure(
                        image=rng.normal(0.0, np.sqrt(variance), (ccd, ccd)).astype(np.float32),
                        wcs=exposure_wcs((float(ra), float(dec)), (ccd, ccd), 0.2, rotation),
                        variance=variance,
                        psf=galsim.Moffat(beta=3.5, fwhm=0.9),
                        visit=1000 * k + visit,
                        detector=detector,
                        band=band,
                        zero_point=30.0,
                    )
                    write_exposure(exposure, path)
    return paths


def _cli(args: list[str], *, fresh: bool = True) -> tuple[float, float, str]:
    """Run ``cellcoadd ARGS`` in a fresh process (its ``--out-dir`` emptied first when
    ``fresh``, so that every run builds everything): wall s, CPU s (it and its
    children), its output."""
    if fresh and "--out-dir" in args:
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
from cellcoadd.execution.settings import DASK_WORKER_CONFIG
dask.config.set(DASK_WORKER_CONFIG)  # as docs/survey-runs.md asks of a cluster
cluster = distributed.LocalCluster(
    n_workers=int(sys.argv[1]), threads_per_worker=1, dashboard_address=":0"
)
print(cluster.scheduler_address, flush=True)
sys.stdin.read()
cluster.close()
"""


def start_cluster(workers: int) -> tuple[subprocess.Popen, str]:
    """A LocalCluster of ``workers`` workers in another process, and its scheduler
    address."""
    process = subprocess.Popen(
        [sys.executable, "-c", _CLUSTER, str(workers)], stdin=subprocess.PIPE,
        stdout=subprocess.PIPE, text=True,
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


def _patch_files(out: Path) -> list[Path]:
    return sorted(out.glob("*/tract_*/patch_*"))


def _hashes(out: Path) -> dict[str, str]:
    """SHA-256 of every patch file, by its path under ``out`` (``<band>/tract_<T>/...``)."""
    return {
        p.relative_to(out).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in _patch_files(out)
    }


def _remove_patch_files(out: Path) -> None:
    """Remove a run's patch files once hashed (its ledger and reports stay): the runs of
    an LSST-sized tract write 8 GB each."""
    for path in _patch_files(out):
        path.unlink()


def _patches_reported(out: Path) -> list[dict]:
    """Every patch the run built, from the tracts' reports (``report.json`` names them)."""
    report = json.loads((out / "report.json").read_text())
    patches = []
    for tract in report["tracts"].values():
        data = json.loads((out / tract["report"]).read_text())
        patches += [p for p in data["patches"] if p["state"] == "done"]
    return patches


def _run_record(out: Path, wall: float, cpu: float, workers: int) -> dict:
    """A run's figures: the patch tasks' CPU and wall (worker seconds, summed over their
    parts), the run's wall less the tasks' wall per worker, the workers' peak RSS."""
    patches = _patches_reported(out)
    task_wall = sum(p.get("wall_s", 0.0) for p in patches)
    return {
        "wall": wall, "cpu": cpu, "tasks": sum(p.get("cpu_s", 0.0) for p in patches),
        "task_wall": task_wall, "outside": wall - task_wall / workers,
        "rss": max(p.get("peak_rss_mb", 0.0) for p in patches),
        "cut": sum(1 for p in patches if p.get("parts", 1) > 1), "built": len(patches),
    }  # fmt: skip


def _up_to_date(out: Path) -> None:
    """Check that the run just made built nothing (every patch up to date)."""
    this_run = json.loads((out / "report.json").read_text())["this_run"]
    assert not this_run["built"] and this_run["up_to_date"] == this_run["planned"], this_run


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


def _median(runs: list[dict], key: str) -> float:
    return float(np.median([r[key] for r in runs]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--visits", type=int, default=12, help="visits (files per patch, band)")
    parser.add_argument("--tracts", type=int, default=1, help="tracts side by side")
    parser.add_argument("--bands", default="r", help="bands, comma-separated (e.g. g,r,i)")
    parser.add_argument("--patches", type=int, default=3, help="patches per tract side")
    parser.add_argument("--cells", type=int, default=4, help="inner cells per patch side")
    parser.add_argument("--ccd", type=int, help="exposure side, px (default: covers a patch)")
    parser.add_argument(
        "--workers", default="2", help="worker counts of the LocalCluster modes (e.g. 2,4,8)"
    )
    parser.add_argument(
        "--scheduler-workers", type=int, default=2, help="workers of the long-lived cluster"
    )
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
    bands = [b.strip() for b in args.bands.split(",") if b.strip()]
    worker_counts = sorted({int(n) for n in args.workers.split(",")})
    if not bands or not worker_counts or min(worker_counts) < 2:
        parser.error("give at least one band and worker counts >= 2")
    print(f"machine: {machine_summary()}")
    per_tract = args.patches**2
    n_patches = args.tracts * len(bands) * per_tract
    print(
        f"job: {args.tracts} tract(s) x {len(bands)} band(s) ({','.join(bands)}) x "
        f"{args.patches} x {args.patches} patches = {n_patches} patches of "
        f"{(args.cells + 2) ** 2} cells (250 x 250 px, K = 3) from "
        f"{args.visits * n_patches} exposure files of {args.ccd} x {args.ccd} px"
    )
    with tempfile.TemporaryDirectory() as temporary:
        work = Path(args.workdir or temporary)
        inputs = work / (
            f"inputs-{args.tracts}t-{''.join(bands)}-{args.patches}p-{args.cells}c-{args.ccd}px"
        )
        inputs.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        paths = write_inputs(
            inputs, args.visits, args.tracts, bands, args.patches, args.cells, args.ccd
        )
        print(f"inputs: {len(paths)} files ready in {time.perf_counter() - start:.1f} s")
        skymap = work / f"skymap-{args.tracts}t-{args.patches}p-{args.cells}c.json"
        skymap.write_text(_skymap(args.tracts, args.patches, args.cells).to_json())
        db = work / f"{inputs.name}.sqlite"
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
        base = ["run", "--index", str(db), "--skymap", str(skymap), "-q", "--no-figure"]
        one_patch = ["--band", bands[0], "--tract", "0", "--patch", "0,0"]
        cluster, address = start_cluster(args.scheduler_workers)
        modes = [("serial", ["--workers", "1"], 1)]
        modes += [(f"workers{n}", ["--workers", str(n)], n) for n in worker_counts]
        modes += [("scheduler", ["--scheduler", address], args.scheduler_workers)]
        try:
            overhead = task_overhead(address)
            # a long-lived cluster has imported and compiled already: one patch to warm it
            _cli([*base, "--out-dir", str(work / "warm-up"), "--scheduler", address,
                  *one_patch])  # fmt: skip
            _remove_patch_files(work / "warm-up")
            results: dict[str, list[dict]] = {}
            hashes: list[dict[str, str]] = []
            client: dict[str, list[float]] = {}
            for round_ in range(args.repeats):
                for mode, extra, workers in modes:
                    out = work / f"out-{mode}-{round_}"
                    idle = idle_cores(0.5)
                    before = _tree_cpu(cluster.pid) if mode == "scheduler" else 0.0
                    wall, cpu, _ = _cli([*base, "--out-dir", str(out), *extra])
                    if mode == "scheduler":
                        cpu += _tree_cpu(cluster.pid) - before
                    record = _run_record(out, wall, cpu, workers)
                    record.update(idle=idle, load=os.getloadavg()[0])
                    results.setdefault(mode, []).append(record)
                    hashes.append(_hashes(out))
                    if mode == "serial":
                        # the client's own work: the same command on the finished
                        # directory (every patch up to date), all tracts and tract 0 alone
                        for name, more in (
                            ("all", ["--workers", "1"]),
                            ("tract 0", ["--workers", "1", "--tract", "0"]),
                            ("all, scheduler", ["--scheduler", address]),
                        ):
                            seconds, _, _ = _cli([*base, "--out-dir", str(out), *more],
                                                 fresh=False)  # fmt: skip
                            _up_to_date(out)
                            client.setdefault(name, []).append(seconds)
                    _remove_patch_files(out)
            # peak RSS of a worker: one whole patch each (two patches on two workers: none
            # cut into parts), then every patch (fresh LocalClusters)
            one = work / "out-one"
            pair = ["--patch", "1,1", "--patch", "0,1"] if args.patches > 1 else ["--patch", "0,0"]
            _cli([*base, "--out-dir", str(one), "--workers", "2", "--band", bands[0], "--tract",
                  "0", *pair])  # fmt: skip
            rss_one = _run_record(one, 0.0, 0.0, 2)["rss"]
            _remove_patch_files(one)
        finally:
            assert cluster.stdin is not None
            cluster.stdin.close()
            cluster.wait(timeout=60)
        # every run, in the order run: the host's speed drifts between rounds
        print()
        print(format_table(
            ["round", "run", "wall s", "CPU s", "tasks' CPU s", "tasks' wall s",
             "wall - tasks' wall / workers", "patches cut", "idle cores before",
             "load 1 min"],
            [[k, mode, r["wall"], r["cpu"], r["tasks"], r["task_wall"], r["outside"], r["cut"],
              r["idle"], r["load"]]
             for k in range(args.repeats) for mode, runs in results.items()
             for r in runs[k : k + 1]],
            ["d", "s", ".1f", ".1f", ".1f", ".1f", ".1f", "d", ".2f", ".2f"],
        ))  # fmt: skip
        rows = []
        serial = {k: _median(results["serial"], k) for k in ("wall", "cpu", "tasks")}
        for mode, runs in results.items():
            rows.append([
                mode, _median(runs, "wall"), _median(runs, "cpu"),
                serial["wall"] / _median(runs, "wall"), _median(runs, "cpu") / serial["cpu"],
                _median(runs, "tasks") / serial["tasks"], _median(runs, "outside"),
                _median(runs, "load"), runs[-1]["rss"],
            ])  # fmt: skip
        print()
        print(format_table(
            ["run (medians)", "wall s", "CPU s", "speed-up", "CPU / serial",
             "tasks' CPU / serial", "wall - tasks' wall / workers", "load 1 min",
             "peak RSS worker MB"], rows,
            ["s", ".1f", ".1f", ".2f", ".2f", ".2f", ".1f", ".2f", ".0f"],
        ))  # fmt: skip
        same = all(h == hashes[0] for h in hashes) and len(hashes[0]) == n_patches
        print(
            f"\noutputs: {len(hashes[0])} patch files per run, "
            f"{'identical' if same else 'DIFFERENT'} across every run and mode"
        )
        print(
            "targets (issue 38): workers2 speed-up >= 1.85x at CPU / serial <= 1.05 "
            f"(CPU per patch, serial: {serial['cpu'] / n_patches:.2f} s; tasks' "
            f"{serial['tasks'] / n_patches:.2f} s)"
        )
        rss_all = _median(results[f"workers{worker_counts[0]}"], "rss")
        print(
            f"peak RSS of a worker: {rss_one:.0f} MB for 1 patch each, {rss_all:.0f} MB for "
            f"{n_patches} patches (ratio {rss_all / rss_one:.2f}, target: flat)"
        )
        every = {name: float(np.median(values)) for name, values in client.items()}
        line = (
            f"client, every patch up to date (medians): {every['all']:.2f} s for "
            f"{args.tracts} tract(s) x {len(bands)} band(s) serial "
            f"({every['all'] / args.tracts:.2f} s per tract), {every['tract 0']:.2f} s "
            f"for tract 0, {every['all, scheduler']:.2f} s on the scheduler"
        )
        if args.tracts > 1:
            extra = (every["all"] - every["tract 0"]) / (args.tracts - 1)
            line += f"; each further tract {extra:.2f} s ({extra / len(bands):.2f} s per band)"
        print(line)
        print(f"scheduler round trip per task: {1000 * overhead:.1f} ms (no-op tasks)")
        median, mean_found, fill = query_time(work / "synthetic.sqlite", args.rows)
        print(
            f"index query at {args.rows:,} rows: {1000 * median:.2f} ms median per LSST patch "
            f"(~{mean_found:.0f} candidate inputs returned; filling took {fill:.0f} s)"
        )


if __name__ == "__main__":
    main()
