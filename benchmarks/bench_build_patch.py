"""Parallel speed-up of ``build_patch`` and proof that the outputs do not depend on it.

The job: the demo field simulation scaled up to a patch of 6 x 6 inner cells plus a ring
of border cells (8 x 8 = 64 cells of 250 x 250 px at 0.2 arcsec/px), observed in 20
dithered visits by the demo focal plane (3 x 3 CCDs of 400 x 400 px at 0.27 arcsec/px:
180 exposures, stars and galaxies, masks, noise), K = 3 noise realizations.

It is built serially in this process, on a local process pool of 2 workers and on a dask
``LocalCluster`` of 2 single-threaded worker processes, with ``build_patch`` as it is and
with the dispatch proposed for it (defined here): the main process finds each cell's
candidate exposures with one batched WCS call per exposure, every worker receives the
exposures once (pool initializer; dask broadcast) and each task carries only a cell and
exposure indices, the exact per-pair overlap test running in the worker. Every cell of a
parallel build must equal the serial one bit for bit (``CellCoadd.equals``). Times are
wall-clock medians of ``--repeats`` builds; speed-ups are against the serial build of the
same run. The last table shows the serial work of the main process and the pickled bytes
the tasks carry.

Run as ``.venv/bin/python benchmarks/bench_build_patch.py [--repeats N] [--visits N]``.
"""

from __future__ import annotations

import os

# one thread per process: the parallelism measured is the one over cells
for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import argparse  # noqa: E402
import logging  # noqa: E402
import pickle  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402

from common import format_table, machine_summary, median_seconds  # noqa: E402

from cellcoadd.build.cell import build_cell  # noqa: E402
from cellcoadd.build.patch import build_patch  # noqa: E402
from cellcoadd.build.select import exposures_near_cells, rough_exposure_box  # noqa: E402
from cellcoadd.geometry import SkyMap, SkyMapConfig  # noqa: E402
from cellcoadd.geometry.tract import Cell  # noqa: E402
from cellcoadd.model.build_config import BuildConfig  # noqa: E402
from cellcoadd.model.cell_coadd import CellCoadd  # noqa: E402
from cellcoadd.model.exposure import Exposure  # noqa: E402
from cellcoadd.model.maskbits import MaskBits  # noqa: E402
from cellcoadd.model.patch_coadd import PatchCoadd  # noqa: E402
from cellcoadd.sim import SimConfig, simulate_field  # noqa: E402

# dask warns about the large task graphs build_patch sends; that is what is measured here
warnings.filterwarnings("ignore", message="Sending large graph", category=UserWarning)

PATCH_INDEX = (1, 1)
CELLS_PER_PATCH = 6


def benchmark_skymap() -> SkyMap:
    """The demo sky map with 6 x 6 inner cells per patch (LSST cell geometry)."""
    config = SkyMapConfig(
        pixel_scale=0.2,
        cell_inner=150,
        cell_border=50,
        cells_per_patch=CELLS_PER_PATCH,
        patches_per_tract=3,
    )
    return SkyMap.from_centers([(60.0, -30.0)], config)


def differing_cells(reference: PatchCoadd, other: PatchCoadd) -> list[tuple[int, int]]:
    """Indices of the cells that are not bit-identical (or missing) in ``other``."""
    if list(reference.cells) != list(other.cells):
        return list(set(reference.cells) ^ set(other.cells))
    return [index for index, cell in reference.cells.items() if not cell.equals(other[index])]


def task_bytes(
    cells: list[Cell], near: list[list[int]], exposures: list[Exposure], block: int
) -> int:
    """Pickled size of the tasks if cells were sent in ``block`` x ``block`` groups.

    ``near[i]`` lists the exposures (indices) sent with ``cells[i]``; an exposure needed by
    several cells of a group is sent once with it.
    """
    groups: dict[tuple[int, int], set[int]] = {}
    for cell, indices in zip(cells, near, strict=True):
        key = (cell.index[0] // block, cell.index[1] // block)
        groups.setdefault(key, set()).update(indices)
    per_exposure = [len(pickle.dumps(exposure, protocol=5)) for exposure in exposures]
    per_cell = len(pickle.dumps((cells[0], BuildConfig(), 0), protocol=5)) * len(cells)
    return per_cell + sum(per_exposure[k] for group in groups.values() for k in group)


# --- the dispatch proposed for build_patch: exposures sent to each worker once ----------

_WORKER_EXPOSURES: list[Exposure] = []  # filled once per pool worker by its initializer


def _keep_exposures(exposures: list[Exposure]) -> None:
    _WORKER_EXPOSURES[:] = exposures


def _build_given(
    cell: Cell, candidates: list[Exposure], config: BuildConfig, seed: int, mask_bits: MaskBits
) -> CellCoadd:
    # the exact per-pair test, in the worker: the main process only made a cheap superset
    near = [e for e in candidates if rough_exposure_box(cell, e) is not None]
    return build_cell(cell, near, config, seed, mask_bits=mask_bits)


def _build_resident(
    cell: Cell, indices: list[int], config: BuildConfig, seed: int, mask_bits: MaskBits
) -> CellCoadd:
    candidates = [_WORKER_EXPOSURES[k] for k in indices]
    return _build_given(cell, candidates, config, seed, mask_bits)


def resident_pool_build(
    cells: list[Cell], exposures: list[Exposure], config: BuildConfig, workers: int
) -> dict[tuple[int, int], CellCoadd]:
    """Cells on a process pool whose workers received the exposures once, at start."""
    near = exposures_near_cells(cells, exposures)
    mask_bits = exposures[0].mask_bits
    with ProcessPoolExecutor(workers, initializer=_keep_exposures, initargs=(exposures,)) as pool:
        futures = [
            pool.submit(_build_resident, cell, indices, config, 1, mask_bits)
            for cell, indices in zip(cells, near, strict=True)
        ]
        return {cell.index: future.result() for cell, future in zip(cells, futures, strict=True)}


def resident_dask_build(
    client: object, cells: list[Cell], exposures: list[Exposure], config: BuildConfig
) -> dict[tuple[int, int], CellCoadd]:
    """Cells on a dask cluster after broadcasting the exposures to every worker once."""
    near = exposures_near_cells(cells, exposures)
    mask_bits = exposures[0].mask_bits
    scattered = client.scatter(exposures, broadcast=True)  # type: ignore[attr-defined]
    futures = [
        client.submit(  # type: ignore[attr-defined]
            _build_given, cell, [scattered[k] for k in indices], config, 1, mask_bits, pure=False
        )
        for cell, indices in zip(cells, near, strict=True)
    ]
    built = client.gather(futures)  # type: ignore[attr-defined]
    client.cancel(scattered)  # type: ignore[attr-defined]
    return {cell.index: result for cell, result in zip(cells, built, strict=True)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--visits", type=int, default=20)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--no-dask", action="store_true", help="skip the dask cluster")
    args = parser.parse_args()

    skymap = benchmark_skymap()
    patch = skymap[0].patch(*PATCH_INDEX)
    cells = patch.cells
    start = time.perf_counter()
    simulation = simulate_field(SimConfig(), skymap, 0, PATCH_INDEX, args.visits, seed=args.seed)
    simulated = time.perf_counter() - start
    exposures = simulation.exposures
    config = BuildConfig(n_noise=3, psf_size=35)
    print(f"build_patch: {len(cells)} cells, {len(exposures)} exposures; {machine_summary()}")
    print(f"simulation {simulated:.1f} s; load average at start {os.getloadavg()[0]:.1f}\n")

    def build(**options: object) -> PatchCoadd:
        return build_patch(patch, exposures, config, seed=1, progress=False, **options)

    def row(name: str, seconds: float, cells_built: dict) -> tuple[str, float, float, str]:
        same = not differing_cells(serial, PatchCoadd(serial.metadata, cells_built))
        return (name, seconds, serial_s / seconds, "yes" if same else "NO")

    serial_s, serial = median_seconds(lambda: build(workers=1), args.repeats)
    rows = [("build_patch, serial (workers=1)", serial_s, 1.0, "reference")]
    pool_s, pooled = median_seconds(lambda: build(workers=2), args.repeats)
    rows.append(row("build_patch, process pool of 2", pool_s, pooled.cells))
    seconds, built = median_seconds(
        lambda: resident_pool_build(cells, exposures, config, 2), args.repeats
    )
    rows.append(row("proposed: pool of 2, exposures sent once", seconds, built))
    if not args.no_dask:
        from distributed import Client, LocalCluster

        with (
            LocalCluster(
                n_workers=2,
                threads_per_worker=1,
                processes=True,
                dashboard_address=":0",
                silence_logs=logging.ERROR,
            ) as cluster,
            Client(cluster) as client,
        ):
            # warm-up: imports and numba cache loads in the workers
            client.gather(
                client.map(
                    _build_given,
                    cells[:2],
                    [exposures[:1]] * 2,
                    [config] * 2,
                    [1] * 2,
                    [exposures[0].mask_bits] * 2,
                )
            )
            dask_s, on_dask = median_seconds(lambda: build(scheduler=client), args.repeats)
            rows.append(row("build_patch, dask LocalCluster 2x1", dask_s, on_dask.cells))
            seconds, built = median_seconds(
                lambda: resident_dask_build(client, cells, exposures, config), args.repeats
            )
            rows.append(row("proposed: dask 2x1, exposures broadcast once", seconds, built))
    n_used = sum(cell.n_used for cell in serial.cells.values())
    n_inputs = sum(len(cell.inputs) for cell in serial.cells.values())
    print(format_table(["run", "wall s", "speed-up", "identical"], rows, ["s", ".1f", ".2f", "s"]))
    print(f"\n{n_inputs} (cell, exposure) candidates, {n_used} used")

    exact_s, near = median_seconds(
        lambda: [
            [k for k, e in enumerate(exposures) if rough_exposure_box(c, e) is not None]
            for c in cells
        ],
        1,
    )
    batched_s, _ = median_seconds(lambda: exposures_near_cells(cells, exposures), 1)
    overhead = [
        ("finding each cell's exposures, per pair (now)", exact_s, "s"),
        ("same, one batched WCS call per exposure", batched_s, "s"),
        (
            "pickled task data, one cell per task (now)",
            task_bytes(cells, near, exposures, 1) / 1e6,
            "MB",
        ),
        (
            "pickled task data, 2 x 2 cells per task",
            task_bytes(cells, near, exposures, 2) / 1e6,
            "MB",
        ),
        (
            "exposures sent once to each of 2 workers",
            2 * sum(len(pickle.dumps(e, protocol=5)) for e in exposures) / 1e6,
            "MB",
        ),
    ]
    print()
    header = ["serial work in the main process", "value", "unit"]
    print(format_table(header, overhead, ["s", ".2f", "s"]))


if __name__ == "__main__":
    main()
