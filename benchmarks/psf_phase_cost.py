"""CPU cost of the PSF across the cell (``BuildConfig.psf_phase`` and ``psf_corners``): the
patch of ``bench_build_patch.py`` built serially without them, with each and with both,
interleaved.

Run as ``.venv/bin/python benchmarks/psf_phase_cost.py [--inside] [--cells 6] [--ccd 400]
[--visits 20] [--psf-size 35] [--rounds 4] [--psf-variation]`` (the defaults: the
demo-sized patch of 64 cells and 180 exposures of 400-pixel CCDs, each with a constant
PSF, ~1 CPU minute; ``--psf-variation``: PSFs varying over the focal plane, so the corner
stamps interpolate the cores between 3 x 3 nodes per exposure region; ``--ccd 2000``: 20
exposures of one 2000-pixel CCD, each serving every cell). Prints the CPU seconds of this
process (the build is serial, so they are the build's, and are less disturbed by other
load than wall-clock times), the wall-clock seconds and the load average (1 min) of each
build, then the medians. With ``--inside``: per build, the CPU time of all of the inputs'
PSF work for the cells less their centre stamps (which every build draws), against the
rest of the same build.
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
    """The CPU time of the PSF across the cell inside each serial build: all of an input's
    PSF work for a cell (``CellBlock._input_psf``) less its centre stamp
    (``coadd_psf_contribution``, which every build draws) is what the corners and the
    phase terms cost (core draws at the nodes, renders, affine maps); it is compared with
    the rest of the same build, which the machine's load disturbs far less than
    comparing separate builds."""
    spent = {"psf": 0.0, "centre": 0.0}
    originals = (cell_module.CellBlock._input_psf, cell_module.coadd_psf_contribution)

    def timed(function, key):
        def call(*args):
            start = time.process_time()
            try:
                return function(*args)
            finally:
                spent[key] += time.process_time() - start

        return call

    cell_module.CellBlock._input_psf = timed(originals[0], "psf")  # type: ignore[method-assign]
    cell_module.coadd_psf_contribution = timed(originals[1], "centre")
    try:
        for corners, phase in ((False, False), (False, True), (True, False), (True, True)):
            config = BuildConfig(n_noise=3, psf_size=psf_size, psf_phase=phase, psf_corners=corners)
            for _ in range(rounds):
                spent.update(psf=0.0, centre=0.0)
                start = time.process_time()
                build_patch(patch, exposures, config, seed=1, progress=False, workers=1)
                total = time.process_time() - start
                extra = spent["psf"] - spent["centre"]
                rest = total - extra
                print(
                    f"  corners {corners!s:5} phase {phase!s:5}  build {total:5.2f} s  "
                    f"centre stamps {spent['centre']:.2f} s  corners + phase terms "
                    f"{extra:.3f} s ({100 * extra / rest:.1f}% of the rest)"
                )
    finally:
        cell_module.CellBlock._input_psf, cell_module.coadd_psf_contribution = originals  # type: ignore[method-assign]


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
    parser.add_argument(
        "--psf-variation",
        action="store_true",
        help="PSFs varying over the focal plane (as `cellcoadd simulate --psf-variation`)",
    )
    args = parser.parse_args()
    warnings.simplefilter("ignore", PsfStampWarning)

    skymap = benchmark_skymap(args.cells)
    patch = skymap[0].patch(*PATCH_INDEX)
    sim_config = simulation_config(args.cells, args.ccd)
    if args.psf_variation:
        field = sim_config.field.model_copy(update={"psf_fwhm_edge": 0.05, "psf_g_edge": 0.01})
        sim_config = sim_config.model_copy(update={"field": field})
    simulation = simulate_field(sim_config, skymap, 0, PATCH_INDEX, args.visits, seed=3)
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
