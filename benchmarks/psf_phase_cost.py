"""CPU cost of the PSF across the cell (``BuildConfig.psf_phase`` and ``psf_corners``): the
patch of ``bench_build_patch.py`` built serially without them, with each and with both,
interleaved.

Run as ``.venv/bin/python benchmarks/psf_phase_cost.py [--inside] [--cells 6] [--ccd 400]
[--visits 20] [--psf-size 35] [--rounds 4]`` (the defaults: the demo-sized patch of 64 cells
and 180 exposures, ~1 CPU minute). Prints the CPU seconds of this process (the build is
serial, so they are the build's, and are less disturbed by other load than wall-clock
times), the wall-clock seconds and the load average (1 min) of each build, then the medians.
"""

from __future__ import annotations

import os

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402

from bench_build_patch import (  # noqa: E402
    PATCH_INDEX,
    benchmark_skymap,
    simulation_config,
    warm_up_cell,
)

import cellcoadd.builder.cell as cell_module  # noqa: E402
from cellcoadd.builder.cell import build_cell  # noqa: E402
from cellcoadd.builder.patch import build_patch  # noqa: E402
from cellcoadd.errors import PsfStampWarning  # noqa: E402
from cellcoadd.model.build_config import BuildConfig  # noqa: E402
from cellcoadd.sim import simulate_field  # noqa: E402


def timed_inside(patch, exposures, psf_size: int, rounds: int) -> None:
    """The CPU time of the phase terms' own calls (core draws, affine maps) and of the PSF
    stamps (centre and corners) against the rest of the same serial build, which the
    machine's load disturbs far less than comparing separate builds."""
    spent = {"phase": 0.0, "stamps": 0.0}
    originals = (cell_module.CellBlock._core, cell_module.input_map,
                 cell_module.coadd_psf_contribution)  # fmt: skip

    def timed(function, key):
        def call(*args):
            start = time.process_time()
            try:
                return function(*args)
            finally:
                spent[key] += time.process_time() - start

        return call

    cell_module.CellBlock._core = timed(originals[0], "phase")  # type: ignore[method-assign]
    cell_module.input_map = timed(originals[1], "phase")
    cell_module.coadd_psf_contribution = timed(originals[2], "stamps")
    try:
        for corners in (False, True):
            config = BuildConfig(n_noise=3, psf_size=psf_size, psf_phase=True, psf_corners=corners)
            for _ in range(rounds):
                spent.update(phase=0.0, stamps=0.0)
                start = time.process_time()
                build_patch(patch, exposures, config, seed=1, progress=False, workers=1)
                total = time.process_time() - start
                rest = total - spent["phase"]
                print(
                    f"  corners {corners!s:5}  build {total:5.2f} s  phase terms "
                    f"{spent['phase']:.3f} s ({100 * spent['phase'] / rest:.1f}% of the rest)"
                    f"  PSF stamps {spent['stamps']:.2f} s"
                )
    finally:
        (cell_module.CellBlock._core, cell_module.input_map,
         cell_module.coadd_psf_contribution) = originals  # type: ignore[method-assign]  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=6, help="inner cells per patch side")
    parser.add_argument("--ccd", type=int, default=400, help="CCD side, pixels")
    parser.add_argument("--visits", type=int, default=20)
    parser.add_argument("--psf-size", type=int, default=35)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument(
        "--inside", action="store_true", help="time the phase terms inside each build instead"
    )
    args = parser.parse_args()
    warnings.simplefilter("ignore", PsfStampWarning)

    skymap = benchmark_skymap(args.cells)
    patch = skymap[0].patch(*PATCH_INDEX)
    simulation = simulate_field(
        simulation_config(args.cells, args.ccd), skymap, 0, PATCH_INDEX, args.visits, seed=3
    )
    exposures = simulation.exposures
    variants = {"none": (False, False), "phase": (False, True), "corners": (True, False),
                "both": (True, True)}  # fmt: skip
    configs = {
        name: BuildConfig(n_noise=3, psf_size=args.psf_size, psf_corners=corners, psf_phase=phase)
        for name, (corners, phase) in variants.items()
    }
    for config in configs.values():  # imports, numba caches
        cell, candidates = warm_up_cell(patch, exposures, config)
        build_cell(cell, candidates, config)
    if args.inside:
        print(f"{len(patch.cells)} cells, {len(exposures)} exposures, psf_size {args.psf_size}")
        timed_inside(patch, exposures, args.psf_size, args.rounds)
        return
    print(
        f"{len(patch.cells)} cells, {len(exposures)} exposures, psf_size {args.psf_size}; "
        "variant, CPU s, wall s, load"
    )
    cpu: dict[str, list[float]] = {name: [] for name in configs}
    for _ in range(args.rounds):
        for name, config in configs.items():
            start_cpu, start = time.process_time(), time.perf_counter()
            build_patch(patch, exposures, config, seed=1, progress=False, workers=1)
            cpu[name].append(time.process_time() - start_cpu)
            wall = time.perf_counter() - start
            print(f"  {name:8}  {cpu[name][-1]:6.2f}  {wall:6.2f}  {os.getloadavg()[0]:.1f}")
    base = statistics.median(cpu["none"])
    print(f"median CPU s: none {base:.2f}")
    for name in ("phase", "corners", "both"):
        value = statistics.median(cpu[name])
        print(f"  {name:8} {value:.2f} ({100 * (value / base - 1):+.1f}%)")


if __name__ == "__main__":
    main()
