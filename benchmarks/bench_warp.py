"""Throughput of the Lanczos-3 warp against scipy and GalSim on one core.

The job: a 250x250 coadd cell at 0.2 arcsec/px resampled from an exposure at
0.26 arcsec/px rotated by 30 deg, with 1, 4 and 6 planes. Rates are output pixels times
planes per second of process CPU time (Mpix-plane/s), the median of repeated,
interleaved runs after a warm-up call; CPU time keeps the per-core figure meaningful on a
shared machine, and a method using several threads is charged for all of them.

``cellcoadd`` is ``warp_planes`` on planes stored one after the other (which it copies
into the interleaved layout first, the copy included); ``interleaved`` is
``accumulate_warped`` on the same planes stored pixel by pixel, the layout ``build_cell``
uses (checked to give the same bits). Runs of all methods alternate, so each call starts
with caches holding the other methods' data; ``inter. warm`` times ``accumulate_warped``
right after an untimed call on the same inputs, as in ``build_cell``, which writes the
input pixels just before warping them (the references are compute-bound: at 10 and 2.6
Mpix-plane/s, warm caches change nothing for them).

References, run on the same job in the same process:

* ``scipy.ndimage.map_coordinates(order=3)``: cubic B-spline, plane by plane (its spline
  prefilter is part of each call), written straight into one output array;
* GalSim ``InterpolatedImage`` with ``Lanczos(3)`` drawn through the cell's WCS with
  ``method="no_pixel"``, plane by plane (construction included: it is needed per plane).

Arithmetic rate
---------------
The same run measures the core's peak and the rate of ``accumulate_warped`` (into a
preallocated ``out``, the way the build calls it) on the rotated job, in GFLOP/s of
process CPU time:

* peak: a numba loop of independent chains of float64 multiply-adds over an array that
  stays in L1, vectorised and contracted to FMA (``fastmath``, for this loop only); an FMA
  counts as 2 FLOP. The best of several runs (a conservative peak: it only makes the
  fractions smaller). numba vectorises it as it vectorises the kernels: on processors
  whose compiler tuning prefers 256-bit vectors (Intel's AVX-512 cores) four doubles at
  a time.
* peak (8 lanes): the same chains written as explicit vectors of eight doubles
  (``llvm.fma.v8f64``), which AVX-512 runs in 512-bit registers: the core's float64
  peak where it is higher. ``% peak8 (72)`` is the fraction of it.
* the kernel, per output pixel and plane: the 6x6 sums, 36 multiplications and 30
  additions for the column sums plus 6 and 5 for the sum across them (77 FLOP), and the
  accumulation ``out += weight * sum`` (2 FLOP); per output pixel, shared by its planes,
  the two sets of six normalised Lanczos weights (``WEIGHT_FLOP``: the multiplications,
  additions, subtractions and the division in
  :func:`cellcoadd.builder.kernels.lanczos.lanczos_taps`, twice; comparisons, selects,
  ``floor`` and integer conversions not counted). So ``79 + WEIGHT_FLOP / P`` FLOP per
  output pixel-plane. ``% peak (72)`` counts only the 72 FLOP of the 36 multiply-adds of
  the taps, a floor on any count.

The rate is measured after the other methods ran (its inputs mostly out of the caches)
and, as ``warm``, right after an untimed run on the same inputs (as the build calls it).

With ``--compete`` the script starts a second process running a Python busy loop and pins
it and itself to the same core (the benchmark's CPU time then shares that core's caches
and time slices with it); the loop is stopped at the end.

Run as ``.venv/bin/python benchmarks/bench_warp.py [--repeats N] [--compete]``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from collections.abc import Callable
from functools import partial

import galsim
import numba
import numpy as np
from common import format_table, machine_summary
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic
from scipy import ndimage

from cellcoadd.builder.kernels.accumulate import accumulate_warped
from cellcoadd.builder.kernels.warp import warp_planes

OUTPUT_SIZE = 250
COADD_SCALE = 0.2  # arcsec / px
EXPOSURE_SCALE = 0.26  # arcsec / px
ROTATION_DEG = 30.0
INPUT_SIZE = 300  # exposure cutout holding the rotated footprint with margin

TAP_FLOP = 77  # per output pixel-plane: 6x6 sums (42 multiplications, 35 additions)
ACCUMULATE_FLOP = 2  # per output pixel-plane: out += weight * sum
WEIGHT_FLOP = 2 * 78  # per output pixel: x and y weights, 48 mul + 29 add/sub + 1 div each
MULTIPLY_ADD_FLOP = 72  # per output pixel-plane: the 36 multiply-adds of the taps alone

_PEAK_CHAIN = 8  # dependent multiply-adds per element and pass
_PEAK_ELEMENTS = 512  # 4 kB: in L1; independent elements fill the vector lanes


@numba.njit(fastmath=True, cache=True)
def _multiply_adds(values: np.ndarray, passes: int, factor: float, offset: float) -> None:
    """``passes * _PEAK_CHAIN`` multiply-adds on every element of ``values``, in place.

    The elements are independent (vector lanes and enough chains in flight to hide the
    latency); each pass reads and writes an element once, 8 FMA per load and store.
    """
    for _ in range(passes):
        for i in range(values.shape[0]):
            value = values[i]
            value = value * factor + offset
            value = value * factor + offset
            value = value * factor + offset
            value = value * factor + offset
            value = value * factor + offset
            value = value * factor + offset
            value = value * factor + offset
            value = value * factor + offset
            values[i] = value


_WIDE = 8  # doubles per explicit vector of the 8-lane peak


@intrinsic
def _fused_chain(typingctx, values, index, factor, offset):
    """``values[index : index + 8] = fma(..., factor, offset)`` applied ``_PEAK_CHAIN``
    times, as one vector of eight doubles."""
    signature = types.void(values, index, factor, offset)

    def codegen(context, builder, signature, args):
        array, index, factor, offset = args
        data = context.make_array(signature.args[0])(context, builder, array).data
        vector_type = ir.VectorType(ir.DoubleType(), _WIDE)
        pointer = builder.bitcast(builder.gep(data, [index]), vector_type.as_pointer())
        fma = builder.module.declare_intrinsic(
            "llvm.fma.v8f64", fnty=ir.FunctionType(vector_type, [vector_type] * 3)
        )
        lanes = ir.Constant(ir.VectorType(ir.IntType(32), _WIDE), [0] * _WIDE)
        splats = []
        for scalar in (factor, offset):
            vector = builder.insert_element(
                ir.Constant(vector_type, ir.Undefined), scalar, ir.Constant(ir.IntType(32), 0)
            )
            splats.append(builder.shuffle_vector(vector, vector, lanes))
        value = builder.load(pointer, align=8)
        for _ in range(_PEAK_CHAIN):
            value = builder.call(fma, [value, *splats])
        builder.store(value, pointer, align=8)
        return context.get_dummy_value()

    return signature, codegen


@numba.njit(cache=True)
def _multiply_adds_wide(values: np.ndarray, passes: int, factor: float, offset: float) -> None:
    """:func:`_multiply_adds` written as explicit vectors of eight doubles."""
    for _ in range(passes):
        for i in range(0, values.shape[0], _WIDE):
            _fused_chain(values, i, factor, offset)


def peak_gflops(repeats: int = 7, passes: int = 20_000, *, wide: bool = False) -> float:
    """The core's float64 multiply-add rate (GFLOP/s of CPU time), best of ``repeats``;
    ``wide``: with explicit vectors of eight doubles."""
    values = np.linspace(0.0, 1.0, _PEAK_ELEMENTS)
    loop = _multiply_adds_wide if wide else _multiply_adds
    loop(values, 1, 0.5, 0.25)  # compile / load from the cache
    best = np.inf
    for _ in range(repeats):
        start = time.process_time()
        loop(values, passes, 0.5, 0.25)  # converges to 0.5: no overflow
        best = min(best, time.process_time() - start)
    return 2 * _PEAK_CHAIN * _PEAK_ELEMENTS * passes / best / 1e9


def start_competitor() -> subprocess.Popen:
    """A Python busy loop in a second process, pinned with this process to this process's
    first allowed core."""
    core = min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {core})
    competitor = subprocess.Popen([sys.executable, "-c", "while True:\n    pass"])
    os.sched_setaffinity(competitor.pid, {core})
    return competitor


def taps_gflops(rate: float) -> float:
    """GFLOP/s of the taps' 72 FLOP alone at ``rate`` Mpix-plane/s."""
    return rate * MULTIPLY_ADD_FLOP / 1e3


def flop_per_pixel_plane(n_planes: int) -> float:
    """The FLOP count of ``accumulate_warped`` per output pixel and plane."""
    return TAP_FLOP + ACCUMULATE_FLOP + WEIGHT_FLOP / n_planes


def make_job(n_planes: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Planes, output->input positions and the input Jacobian (input px per output px).

    The output centre maps to the input centre (GalSim's convention for drawing an
    ``InterpolatedImage``), so all three methods do the same job.
    """
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:INPUT_SIZE, 0:INPUT_SIZE].astype(np.float64)
    smooth = np.exp(-((xx - 150.3) ** 2 + (yy - 148.7) ** 2) / (2 * 6.0**2))
    planes = np.concatenate(
        [smooth[np.newaxis], rng.normal(size=(n_planes - 1, INPUT_SIZE, INPUT_SIZE))]
    )
    theta = np.radians(ROTATION_DEG)
    rotation = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    jacobian = COADD_SCALE / EXPOSURE_SCALE * rotation
    out_y, out_x = np.mgrid[0:OUTPUT_SIZE, 0:OUTPUT_SIZE].astype(np.float64)
    out_x -= (OUTPUT_SIZE - 1) / 2
    out_y -= (OUTPUT_SIZE - 1) / 2
    centre_in = (INPUT_SIZE - 1) / 2
    x_src = centre_in + jacobian[0, 0] * out_x + jacobian[0, 1] * out_y
    y_src = centre_in + jacobian[1, 0] * out_x + jacobian[1, 1] * out_y
    return planes, x_src, y_src, jacobian


def warp_ours(
    planes: np.ndarray, x_src: np.ndarray, y_src: np.ndarray, _: np.ndarray
) -> np.ndarray:
    return warp_planes(planes, x_src, y_src)


def warp_ours_interleaved(
    pixels: np.ndarray, x_src: np.ndarray, y_src: np.ndarray, _: np.ndarray
) -> np.ndarray:
    out = np.zeros((pixels.shape[2], *x_src.shape))
    return accumulate_warped(pixels, x_src, y_src, out, np.ones(pixels.shape[2]))


def accumulate_into(
    pixels: np.ndarray, x_src: np.ndarray, y_src: np.ndarray, out: np.ndarray
) -> np.ndarray:
    """``accumulate_warped`` alone, into a preallocated ``out`` (as the build calls it)."""
    return accumulate_warped(pixels, x_src, y_src, out, np.ones(pixels.shape[2]))


def warp_scipy(
    planes: np.ndarray, x_src: np.ndarray, y_src: np.ndarray, _: np.ndarray
) -> np.ndarray:
    coordinates = np.stack([y_src, x_src])
    result = np.empty((planes.shape[0], *x_src.shape))
    for plane, output in zip(planes, result, strict=True):
        ndimage.map_coordinates(plane, coordinates, output=output, order=3)
    return result


def alternating_medians(
    calls: dict[str, Callable[[], object]], repeats: int, warm: set[str]
) -> dict[str, float]:
    """Median CPU time (s) of each call; runs alternate so load drifts hit all.

    A call named in ``warm`` is timed right after an untimed run of itself.
    """
    durations: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            if name in warm:
                call()
            start = time.process_time()
            call()
            durations[name].append(time.process_time() - start)
    return {name: float(np.median(values)) for name, values in durations.items()}


def warp_galsim(
    planes: np.ndarray, x_src: np.ndarray, y_src: np.ndarray, jacobian: np.ndarray
) -> np.ndarray:
    # World coordinates: arcsec with the cell's pixel axes; the exposure Jacobian is
    # d(world)/d(input px) = COADD_SCALE * jacobian^-1.
    to_world = COADD_SCALE * np.linalg.inv(jacobian)
    exposure_wcs = galsim.JacobianWCS(
        to_world[0, 0], to_world[0, 1], to_world[1, 0], to_world[1, 1]
    )
    cell_wcs = galsim.PixelScale(COADD_SCALE)
    interpolant = galsim.Lanczos(3)
    result = np.empty((planes.shape[0], *x_src.shape))
    for p, plane in enumerate(planes):
        profile = galsim.InterpolatedImage(
            galsim.ImageD(plane, wcs=exposure_wcs),
            x_interpolant=interpolant,
            normalization="sb",
            calculate_stepk=False,
            calculate_maxk=False,
        )
        image = profile.drawImage(
            nx=x_src.shape[1], ny=x_src.shape[0], wcs=cell_wcs, method="no_pixel"
        )
        # "sb" pixel values are surface brightness; no_pixel drawing multiplies by the
        # output pixel area.
        result[p] = image.array / COADD_SCALE**2
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument(
        "--compete", action="store_true", help="share the core with a Python busy loop"
    )
    args = parser.parse_args()
    numba.set_num_threads(1)  # per-core figure
    competitor = start_competitor() if args.compete else None
    try:
        run(args.repeats, competitor)
    finally:
        if competitor is not None:
            competitor.kill()
            competitor.wait()


def run(repeats: int, competitor: subprocess.Popen | None) -> None:
    """Measure and print the tables (module docstring)."""
    methods = {
        "cellcoadd": warp_ours,
        "interleaved": warp_ours_interleaved,
        "inter. warm": warp_ours_interleaved,
        "scipy o3": warp_scipy,
        "galsim L3": warp_galsim,
    }
    n_pixels = OUTPUT_SIZE * OUTPUT_SIZE
    load_start = os.getloadavg()[0]
    peak = peak_gflops()
    peak_wide = peak_gflops(wide=True)
    print(
        f'warp: {OUTPUT_SIZE}x{OUTPUT_SIZE} output, {COADD_SCALE}"/px from {EXPOSURE_SCALE}"/px '
        f"rotated {ROTATION_DEG:g} deg; 1 numba thread; median CPU time of {repeats}; "
        f"{machine_summary()}; load average (1 min) {load_start:.2f} at start"
        + (
            f"; sharing CPU {min(os.sched_getaffinity(0))} with a busy loop"
            if competitor is not None
            else ""
        )
    )
    print(
        "rates in Mpix-plane/s; interleaved: accumulate_warped, as the build calls it; "
        "inter. warm: the same right after a run on the same inputs (as in the build); "
        "ours = cellcoadd (warp_planes); max diff gs: largest |ours - galsim| on the smooth "
        "plane\n"
    )
    rows = []
    flop_rows = []
    for n_planes in (1, 4, 6):
        job = make_job(n_planes, seed=n_planes)
        # the build's layout: all planes of an input pixel side by side
        pixels = np.ascontiguousarray(job[0].transpose(1, 2, 0))
        calls = {name: partial(function, *job) for name, function in methods.items()}
        calls["interleaved"] = calls["inter. warm"] = partial(
            warp_ours_interleaved, pixels, *job[1:]
        )
        out = np.zeros((n_planes, OUTPUT_SIZE, OUTPUT_SIZE))
        calls["accumulate"] = calls["acc. warm"] = partial(
            accumulate_into, pixels, job[1], job[2], out
        )
        results = {name: call() for name, call in calls.items()}  # warm-up
        if not np.array_equal(results["interleaved"], results["cellcoadd"]):
            raise AssertionError("the interleaved kernel differs from warp_planes")
        seconds = alternating_medians(calls, repeats, warm={"inter. warm", "acc. warm"})
        rates = {name: n_pixels * n_planes / seconds[name] / 1e6 for name in calls}
        flop = flop_per_pixel_plane(n_planes)
        gflops = rates["accumulate"] * flop / 1e3
        flop_rows.append(
            (
                n_planes,
                flop,
                rates["accumulate"],
                gflops,
                100 * gflops / peak,
                100 * taps_gflops(rates["accumulate"]) / peak,
                100 * taps_gflops(rates["accumulate"]) / peak_wide,
                rates["acc. warm"],
                100 * taps_gflops(rates["acc. warm"]) / peak,
            )
        )
        difference = np.abs(results["cellcoadd"][0] - results["galsim L3"][0]).max()
        rows.append(
            (
                n_planes,
                *(rates[name] for name in methods),
                rates["cellcoadd"] / rates["scipy o3"],
                rates["cellcoadd"] / rates["galsim L3"],
                rates["inter. warm"] / rates["galsim L3"],
                difference,
            )
        )
    header = ["planes", *methods, "ours/scipy", "ours/galsim", "warm/galsim", "max diff gs"]
    formats = ["d", *[".2f"] * (len(header) - 2), ".1e"]
    print(format_table(header, rows, formats))
    print(
        f"\naccumulate_warped into a preallocated out (rotated job), against the core's peak "
        f"of {peak:.1f} GFLOP/s (float64 FMA loop as numba vectorises it, best of 7) and "
        f"{peak_wide:.1f} GFLOP/s (the same in vectors of 8 doubles); FLOP/px-plane = "
        f"{TAP_FLOP} + {ACCUMULATE_FLOP} + {WEIGHT_FLOP}/P (module docstring)\n"
    )
    flop_header = [
        "planes",
        "FLOP/px-plane",
        "Mpix-plane/s",
        "GFLOP/s",
        "% peak",
        "% peak (72)",
        "% peak8 (72)",
        "warm Mpix-plane/s",
        "warm % peak (72)",
    ]
    flop_formats = ["d", ".1f", ".1f", ".2f", ".1f", ".1f", ".1f", ".1f", ".1f"]
    print(format_table(flop_header, flop_rows, flop_formats))
    print(
        "(warm: timed right after an untimed run on the same inputs, as the build calls it; "
        "the other columns: after the other methods, inputs mostly out of the caches)"
    )
    print(f"\nload average (1 min) at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
