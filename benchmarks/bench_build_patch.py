"""Parallel speed-up of ``build_patch`` and proof that the outputs do not depend on it.

The job (default): the demo field simulation scaled up to a patch of 10 x 10 inner cells
plus a ring of border cells (12 x 12 = 144 cells of 250 x 250 px at 0.2 arcsec/px),
observed in 20 dithered visits by a focal plane of 2 x 2 CCDs of 1000 x 1000 px at 0.27
arcsec/px (80 exposures, stars and galaxies, masks, noise), K = 3 noise realizations.
``--cells`` and ``--ccd`` change the patch and CCD sizes (``--cells 6 --ccd 400``: the
demo's 3 x 3 CCDs of 400 px, 64 cells); the focal plane gets enough CCDs to cover the
patch at every dither.

``build_patch`` builds it serially in this process, on its own process pool of 2 workers
and on a dask ``LocalCluster`` of 2 single-threaded worker processes started the way a
user should start it for cellcoadd: with ``MALLOC_MMAP_THRESHOLD_`` added to
``distributed.nanny.pre-spawn-environ`` (``--dask-default-malloc`` adds a row on a cluster
started with dask's own settings). Every cell of a parallel build must equal the serial
one bit for bit (``CellCoadd.equals``). Times are wall-clock medians of ``--repeats``
builds; speed-ups are against the serial build of the same run; the load average (1 min)
is read after each measurement. The main process and the dask workers are warmed up by
building one cell first (imports, numba caches); the process pool pays for its start in
every build, as it does for a user. The last table shows the fixed costs: mapping each
exposure onto the patch once and finding each cell's exposures from that, the pickled
bytes the tasks carry and the exposures every worker receives once (with the time dask
takes to send them when nothing else runs; in a build the cells start while they travel).

Run as ``.venv/bin/python benchmarks/bench_build_patch.py [--repeats N] [--cells N]
[--ccd PIXELS] [--visits N]``.
"""

from __future__ import annotations

import os

# one thread per process: the parallelism measured is the one over cells
for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import argparse  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import pickle  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from typing import Any  # noqa: E402

from common import format_table, machine_summary, median_seconds  # noqa: E402

from cellcoadd.builder.cell import build_cell  # noqa: E402
from cellcoadd.builder.inputs import prepare  # noqa: E402
from cellcoadd.builder.patch import build_patch  # noqa: E402
from cellcoadd.geometry import SkyMap, SkyMapConfig  # noqa: E402
from cellcoadd.geometry.tract import Cell, Patch  # noqa: E402
from cellcoadd.model.build_config import BuildConfig  # noqa: E402
from cellcoadd.model.exposure import Exposure  # noqa: E402
from cellcoadd.model.patch_coadd import PatchCoadd  # noqa: E402
from cellcoadd.sim import SimConfig, simulate_field  # noqa: E402

PATCH_INDEX = (1, 1)
PIXEL_SCALE = 0.2  # coadd, arcsec/px

#: What a user adds to the dask configuration before starting a cluster for cellcoadd:
#: glibc keeps arrays below 32 MB on its heap instead of mapping and unmapping each one,
#: which dask's own ``MALLOC_TRIM_THRESHOLD_`` setting would otherwise make it do.
DASK_MALLOC = {"distributed.nanny.pre-spawn-environ.MALLOC_MMAP_THRESHOLD_": 33554432}


def benchmark_skymap(cells_per_patch: int) -> SkyMap:
    """The demo sky map with ``cells_per_patch`` squared inner cells per patch."""
    config = SkyMapConfig(
        pixel_scale=PIXEL_SCALE,
        cell_inner=150,
        cell_border=50,
        cells_per_patch=cells_per_patch,
        patches_per_tract=3,
    )
    return SkyMap.from_centers([(60.0, -30.0)], config)


def simulation_config(cells_per_patch: int, ccd_pixels: int) -> SimConfig:
    """The demo simulation with ``ccd_pixels`` square CCDs, enough to cover the patch.

    The focal plane must span the patch with its border cells plus the dither diameter;
    for 6 cells and 400-px CCDs that is the demo's 3 x 3.
    """
    default = SimConfig()
    field = default.field
    cell_arcsec = 150 * PIXEL_SCALE
    span = (cells_per_patch + 2) * cell_arcsec + 2 * field.dither_radius  # arcsec
    ccd_span = (ccd_pixels + field.ccd_gap) * default.pixel_scale
    n_ccd = max(1, math.ceil(span / ccd_span))
    sides = {"n_ccd_x": n_ccd, "n_ccd_y": n_ccd, "ccd_nx": ccd_pixels, "ccd_ny": ccd_pixels}
    return default.model_copy(update={"field": field.model_copy(update=sides)})


def differing_cells(reference: PatchCoadd, other: PatchCoadd) -> list[tuple[int, int]]:
    """Indices of the cells that are not bit-identical (or missing) in ``other``."""
    if list(reference.cells) != list(other.cells):
        return list(set(reference.cells) ^ set(other.cells))
    return [index for index, cell in reference.cells.items() if not cell.equals(other[index])]


def load() -> float:
    """Load average over the last minute."""
    return os.getloadavg()[0]


def exposures_near_cells(
    patch: Patch, exposures: list[Exposure], config: BuildConfig
) -> list[list[int]]:
    """For each cell of ``patch``, the indices of the exposures that may serve it, as
    ``build_patch`` decides it: each exposure mapped once onto the patch."""
    build = prepare(patch.cells, exposures, config, 0, one_band=True, area=patch.outer_bbox)
    return [build.candidates([cell]) for cell in patch.cells]


def warm_up_cell(
    patch: Patch, exposures: list[Exposure], config: BuildConfig
) -> tuple[Cell, list[Exposure]]:
    """A cell of ``patch`` and its candidate exposures: building it loads what a build needs."""
    cells = patch.cells
    near = exposures_near_cells(patch, exposures, config)
    busiest = max(range(len(cells)), key=lambda i: len(near[i]))
    return cells[busiest], [exposures[k] for k in near[busiest]]


def run_on_dask(
    build: Callable[..., PatchCoadd],
    warm_up: tuple[Cell, list[Exposure]],
    config: BuildConfig,
    exposures: list[Exposure],
    repeats: int,
    settings: dict[str, Any],
) -> tuple[float, PatchCoadd, float, str]:
    """Median build time on a fresh 2 x 1 ``LocalCluster`` started with dask ``settings``,
    its last build, the time to send the exposures to both its workers alone and the
    workers' ``MALLOC_MMAP_THRESHOLD_``."""
    import dask
    from distributed import Client, LocalCluster

    environment = dict(os.environ)
    try:
        with dask.config.set(settings):  # read by the nannies when the cluster starts
            cluster = LocalCluster(
                n_workers=2,
                threads_per_worker=1,
                processes=True,
                dashboard_address=":0",
                silence_logs=logging.ERROR,
            )
    finally:
        # the nannies copy their settings into this process's environment, where the
        # workers of the next cluster would inherit them
        os.environ.clear()
        os.environ.update(environment)
    with cluster, Client(cluster) as client:
        worker_setting = client.run(lambda: os.environ.get("MALLOC_MMAP_THRESHOLD_"))
        thresholds = set(worker_setting.values())
        cell, candidates = warm_up
        client.run(build_cell, cell, candidates, config)
        seconds, built = median_seconds(lambda: build(scheduler=client), repeats)
        start = time.perf_counter()
        table = client.scatter(exposures, hash=False)
        client.replicate(table)  # as build_patch does, but here with no task running
        send_s = time.perf_counter() - start
        client.cancel(table)
    return seconds, built, send_s, ", ".join(sorted(str(value) for value in thresholds))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--cells", type=int, default=10, help="inner cells per patch side")
    parser.add_argument("--ccd", type=int, default=1000, help="CCD side, pixels")
    parser.add_argument("--visits", type=int, default=20)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--no-dask", action="store_true", help="skip the dask cluster")
    parser.add_argument(
        "--dask-default-malloc",
        action="store_true",
        help="also build on a cluster started with dask's default malloc settings",
    )
    args = parser.parse_args()

    skymap = benchmark_skymap(args.cells)
    patch = skymap[0].patch(*PATCH_INDEX)
    cells = patch.cells
    simulation_settings = simulation_config(args.cells, args.ccd)
    start = time.perf_counter()
    simulation = simulate_field(
        simulation_settings, skymap, 0, PATCH_INDEX, args.visits, seed=args.seed
    )
    simulated = time.perf_counter() - start
    exposures = simulation.exposures
    field = simulation_settings.field
    config = BuildConfig(n_noise=3, psf_size=35)
    print(
        f"build_patch: {len(cells)} cells, {len(exposures)} exposures "
        f"({args.visits} visits x {field.n_ccd_x} x {field.n_ccd_y} CCDs of "
        f"{args.ccd} x {args.ccd} px); {machine_summary()}"
    )
    print(f"simulation {simulated:.1f} s; load average at start {load():.1f}\n")

    def build(**options: object) -> PatchCoadd:
        return build_patch(patch, exposures, config, seed=1, progress=False, **options)

    def row(name: str, seconds: float, built: PatchCoadd) -> tuple[str, float, float, str, float]:
        same = "NO" if differing_cells(serial, built) else "yes"
        return (name, seconds, serial_s / seconds, same, load())

    warm_up = warm_up_cell(patch, exposures, config)
    build_cell(warm_up[0], warm_up[1], config)
    serial_s, serial = median_seconds(lambda: build(workers=1), args.repeats)
    rows = [("build_patch, serial (workers=1)", serial_s, 1.0, "reference", load())]
    seconds, built = median_seconds(lambda: build(workers=2), args.repeats)
    rows.append(row("build_patch, process pool of 2", seconds, built))
    send_s = math.nan
    if not args.no_dask:
        dask_runs = [DASK_MALLOC, {}] if args.dask_default_malloc else [DASK_MALLOC]
        for settings in dask_runs:
            seconds, built, send, threshold = run_on_dask(
                build, warm_up, config, exposures, args.repeats, settings
            )
            name = f"build_patch, dask LocalCluster 2x1, MALLOC_MMAP_THRESHOLD_={threshold}"
            rows.append(row(name, seconds, built))
            send_s = send if math.isnan(send_s) else send_s
    header = ["run", "wall s", "speed-up", "identical", "load"]
    print(format_table(header, rows, ["s", ".1f", ".2f", "s", ".1f"]))
    n_used = sum(cell.n_used for cell in serial.cells.values())
    n_inputs = sum(len(cell.inputs) for cell in serial.cells.values())
    print(f"\n{n_inputs} (cell, exposure) candidates, {n_used} used")

    search_s, near = median_seconds(lambda: exposures_near_cells(patch, exposures, config), 3)
    mask_bits = exposures[0].mask_bits
    # a task carries its cell and exposure indices (pool) or references (dask), no pixels
    task_bytes = sum(
        len(pickle.dumps((cell, indices, config, 1, mask_bits), protocol=5))
        for cell, indices in zip(cells, near, strict=True)
    )
    exposure_bytes = sum(len(pickle.dumps(e, protocol=5)) for e in exposures)
    fixed = [
        ("mapping the exposures onto the patch, finding each cell's", search_s, "s"),
        ("pickled task data, all cells", task_bytes / 1e6, "MB"),
        ("exposures sent once to each of 2 workers", 2 * exposure_bytes / 1e6, "MB"),
        ("sending them to 2 dask workers, alone", send_s, "s"),
    ]
    print()
    print(format_table(["fixed costs", "value", "unit"], fixed, ["s", ".2f", "s"]))


if __name__ == "__main__":
    main()
