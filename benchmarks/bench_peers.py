"""cellcoadd against SWarp and scipy on a real LSST patch, whole process: CPU s per job.

Two jobs, each on one core per code:

1. **The realistic job (default, first):** an LSST-sized patch of ``--cells-per-patch``
   (default 20) inner cells per side plus the border ring (484 cells of 150 px inner + 2 x
   50 px border at 0.2 arcsec/px; 3400 px across the outer boxes) from ``--exposures``
   (default 6) FITS exposure files of ``--size`` (default 3800) px at 0.26 arcsec/px, rotated
   (within 10 degrees) and dithered, each covering the patch. Whole process from the files
   to a written coadd, for every code:

   * ``cellcoadd build`` (the command, in a fresh process: headers, reads, build, HDF5
     write), K = 0 and K = 3 noise realizations, PSF stamps and moments included;
   * SWarp (when installed: Debian package ``swarp``; skipped with a message otherwise) on
     the same pixels written as plain FITS images with weight maps (SWarp would take every
     extension of a multi-extension exposure file for an image of its own), one call
     (``NTHREADS 1``, ``RESAMPLING_TYPE LANCZOS3``, ``COMBINE_TYPE WEIGHTED``, no background
     pass) onto the grid covering every cell's outer box, written as FITS;
   * scipy + astropy in a fresh process: reads the same FITS files, maps the grid through
     astropy's WCS into each, ``scipy.ndimage.map_coordinates(order=3)``, weighted mean,
     written as FITS.

   Then cellcoadd's CPU by stage (header and read, mapping, selection, input planes with
   noise generation, mask interpolation, PSF draw, PSF warp, PSF moments, warp kernel,
   accumulation, finishing, write), from one K = 3 build (``--stages-noise 0,3``: one
   K = 0 build too) in this process, each stage's functions wrapped with a CPU clock
   (nested stages subtracted; what no stage claims is "other build").

2. **The small job (second):** today's 36-cell patch (6 x 6 cells) from in-memory
   exposures of ``--small-size`` px, ``build_patch`` against the same peers (GalSim and
   reproject too), then one inner cell alone. Its inputs hold many times the grid's pixels,
   so it flatters cellcoadd against SWarp: the realistic job is the headline.

CPU seconds are the code's process (``getrusage`` of the child, or ``time.process_time``
in this process), medians of ``--rounds`` interleaved rounds (every code once per round).
Ratios are against SWarp in the same run. The machine line lists the CPU's vector
extensions and the load average, printed after every round: on a shared machine, CPU
seconds grow with contention too (shared caches and memory bandwidth), so ratios from a
loaded machine are not the idle-machine figures.

Run as ``.venv/bin/python benchmarks/bench_peers.py [--rounds N] [--cells-per-patch N]
[--exposures N] [--size PX] [--no-small] [--no-stages] [--stages-noise K,...]
[--workdir DIR]``; e.g. the smallest
sensible realistic job: ``--cells-per-patch 4 --size 1400``.
"""

from __future__ import annotations

import os

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import fitsio  # noqa: E402
import galsim  # noqa: E402
import numpy as np  # noqa: E402
from astropy.wcs import WCS  # noqa: E402
from common import exposure_wcs, format_table, machine_summary  # noqa: E402
from scipy import ndimage  # noqa: E402

from cellcoadd.builder.cell import build_cell  # noqa: E402
from cellcoadd.builder.patch import build_patch  # noqa: E402
from cellcoadd.geometry import SkyMap, SkyMapConfig  # noqa: E402
from cellcoadd.model.build_config import BuildConfig  # noqa: E402
from cellcoadd.model.exposure import Exposure  # noqa: E402

PIXEL_SCALE = 0.2  # coadd, arcsec/px
EXPOSURE_SCALE = 0.26
CENTER = (60.0, -30.0)
VECTOR_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512bw", "avx512vl", "avx512_vnni")


def cpu_features() -> str:
    """The vector extensions among the CPU flags of ``/proc/cpuinfo`` (or 'unknown')."""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("flags"):
                    flags = set(line.split(":", 1)[1].split())
                    return ", ".join(flag for flag in VECTOR_FLAGS if flag in flags) or "none"
    except OSError:
        pass
    return "unknown"


def make_exposures(
    patch_center: tuple[float, float],
    n: int,
    size: int,
    *,
    max_rotation: float = 180.0,
    max_offset: float = 20.0,
) -> list[Exposure]:
    """``n`` exposures of ``size`` px with noise and a few hundred stars, all covering the
    patch: rotated by up to ``max_rotation`` degrees, dithered by up to ``max_offset``
    arcsec per axis."""
    rng = np.random.default_rng(7)
    exposures = []
    for visit in range(n):
        dx, dy = rng.uniform(-max_offset, max_offset, 2) / 3600.0
        center = (patch_center[0] + dx / np.cos(np.radians(patch_center[1])), patch_center[1] + dy)
        rotation = rng.uniform(-max_rotation, max_rotation)
        wcs = exposure_wcs(center, (size, size), EXPOSURE_SCALE, rotation)
        image = rng.normal(0.0, 1.0, (size, size)).astype(np.float32)
        n_stars = max(300, size * size // 50_000)
        for x, y, flux in zip(
            *rng.uniform(0, size, (2, n_stars)), rng.uniform(20, 500, n_stars), strict=True
        ):
            x0, y0 = int(x), int(y)
            sl = (
                slice(max(y0 - 8, 0), min(y0 + 9, size)),
                slice(max(x0 - 8, 0), min(x0 + 9, size)),
            )
            yy, xx = np.mgrid[sl]
            image[sl] += flux * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.6**2))
        exposures.append(
            Exposure(
                image=image,
                wcs=wcs,
                variance=1.0 + 0.1 * visit,
                psf=galsim.Moffat(beta=3.5, fwhm=0.8 + 0.05 * visit),
                visit=visit,
                detector=0,
                band="r",
                zero_point=30.0,
            )
        )
    return exposures


def grid_wcs(patch) -> tuple[WCS, tuple[int, int]]:  # type: ignore[no-untyped-def]
    """WCS and shape of one image covering the outer boxes of all the patch's cells."""
    boxes = [cell.outer_bbox for cell in patch.cells]
    x0, y0 = min(b.x_start for b in boxes), min(b.y_start for b in boxes)
    x1, y1 = max(b.x_stop for b in boxes), max(b.y_stop for b in boxes)
    wcs = patch.tract.wcs.deepcopy()
    wcs.wcs.crpix = [wcs.wcs.crpix[0] - x0, wcs.wcs.crpix[1] - y0]
    wcs.wcs.set()
    return wcs, (y1 - y0, x1 - x0)


def child_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def swarp_program() -> str | None:
    return shutil.which("swarp") or shutil.which("SWarp")


def write_plain_fits(exposures: list[Exposure], work: Path) -> list[str]:
    """Each exposure as a plain FITS image ``exp<visit>.fits`` (TAN header) with its weight
    map ``exp<visit>.weight.fits`` (inverse variance): the inputs SWarp and scipy read."""
    names = []
    for exposure in exposures:
        header = [{"name": k, "value": v} for k, v in exposure.wcs.to_header().items()]
        name = work / f"exp{exposure.visit}.fits"
        fitsio.write(str(name), exposure.image, header=header, clobber=True)
        weight = np.full(exposure.image.shape, 1.0 / float(exposure.variance), np.float32)
        fitsio.write(
            str(work / f"exp{exposure.visit}.weight.fits"), weight, header=header, clobber=True
        )
        names.append(str(name))
    return names


def swarp_runner(exposures: list[Exposure], wcs: WCS, shape: tuple[int, int], work: Path):  # type: ignore[no-untyped-def]
    """A function running SWarp on ``exposures`` onto the grid (None if SWarp is missing)."""
    if swarp_program() is None:
        return None
    return swarp_files_runner(write_plain_fits(exposures, work), wcs, shape, work)


def swarp_files_runner(names: list[str], wcs: WCS, shape: tuple[int, int], work: Path):  # type: ignore[no-untyped-def]
    """A function running SWarp on the FITS files ``names`` (weight maps beside them)
    onto the grid ``wcs``, ``shape``, writing its coadd in ``work``."""
    program = swarp_program()
    assert program is not None
    ra, dec = wcs.wcs_pix2world([[(shape[1] - 1) / 2, (shape[0] - 1) / 2]], 0)[0]
    config = {
        "IMAGEOUT_NAME": str(work / "swarp.fits"),
        "WEIGHTOUT_NAME": str(work / "swarp.weight.fits"),
        "WEIGHT_TYPE": "MAP_WEIGHT",
        "WEIGHT_SUFFIX": ".weight.fits",
        "COMBINE": "Y",
        "COMBINE_TYPE": "WEIGHTED",
        "RESAMPLE": "Y",
        "RESAMPLE_DIR": str(work),
        "RESAMPLING_TYPE": "LANCZOS3",
        "CENTER_TYPE": "MANUAL",
        "CENTER": f"{ra:.10f},{dec:.10f}",
        "PIXELSCALE_TYPE": "MANUAL",
        "PIXEL_SCALE": f"{PIXEL_SCALE}",
        "IMAGE_SIZE": f"{shape[1]},{shape[0]}",
        "PROJECTION_TYPE": "TAN",
        "CELESTIAL_TYPE": "NATIVE",
        "SUBTRACT_BACK": "N",
        "NTHREADS": "1",
        "VERBOSE_TYPE": "QUIET",
        "WRITE_XML": "N",
        "DELETE_TMPFILES": "Y",
    }
    config_path = work / "swarp.conf"
    config_path.write_text("".join(f"{key:<16} {value}\n" for key, value in config.items()))

    def run() -> None:
        subprocess.run([program, *names, "-c", str(config_path)], check=True, cwd=work)

    return run


def scipy_coadd(exposures: list[Exposure], wcs: WCS, shape: tuple[int, int]) -> np.ndarray:
    """Weighted mean of the exposures mapped with astropy and cubic splines (scipy)."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    ra, dec = wcs.wcs_pix2world(xx.ravel(), yy.ravel(), 0)
    total = np.zeros(shape)
    weights = 0.0
    for exposure in exposures:
        x, y = exposure.wcs.wcs_world2pix(ra, dec, 0)
        warped = ndimage.map_coordinates(exposure.image, [y, x], order=3, mode="constant")
        weight = 1.0 / float(exposure.variance)
        total += weight * warped.reshape(shape)
        weights += weight
    return total / weights


def galsim_wcs(wcs: WCS) -> galsim.GSFitsWCS:
    """The TAN ``wcs`` as a GalSim WCS (explicit CD matrix)."""
    cd = wcs.wcs.get_pc() * wcs.wcs.get_cdelt()[:, None]
    header = {"CTYPE1": "RA---TAN", "CTYPE2": "DEC--TAN"}
    for axis in (1, 2):
        header[f"CRPIX{axis}"] = float(wcs.wcs.crpix[axis - 1])
        header[f"CRVAL{axis}"] = float(wcs.wcs.crval[axis - 1])
        for other in (1, 2):
            header[f"CD{axis}_{other}"] = float(cd[axis - 1, other - 1])
    return galsim.GSFitsWCS(header=header)


def galsim_coadd(exposures: list[Exposure], wcs: WCS, shape: tuple[int, int]) -> np.ndarray:
    """Weighted mean of the exposures drawn through GalSim ``InterpolatedImage`` + Lanczos(3)."""
    out_wcs = galsim_wcs(wcs)
    total = np.zeros(shape)
    weights = 0.0
    for exposure in exposures:
        in_wcs = galsim_wcs(exposure.wcs)
        image = galsim.Image(exposure.image.astype(np.float64), wcs=in_wcs)
        profile = galsim.InterpolatedImage(
            image,
            x_interpolant=galsim.Lanczos(3),
            calculate_stepk=False,
            calculate_maxk=False,
            use_true_center=False,
        )
        drawn = galsim.Image(shape[1], shape[0], wcs=out_wcs)
        profile.drawImage(drawn, method="no_pixel", add_to_image=False)
        weight = 1.0 / float(exposure.variance)
        total += weight * drawn.array
        weights += weight
    return total / weights


def reproject_coadd(exposures: list[Exposure], wcs: WCS, shape: tuple[int, int]) -> np.ndarray:
    from reproject import reproject_interp  # optional

    total = np.zeros(shape)
    weights = 0.0
    for exposure in exposures:
        warped, _ = reproject_interp(
            (exposure.image, exposure.wcs), wcs, shape_out=shape, order="bicubic"
        )
        weight = 1.0 / float(exposure.variance)
        total += weight * np.nan_to_num(warped)
        weights += weight
    return total / weights


def compare(codes: dict[str, Callable[[], object]], rounds: int, area: float, unit: str) -> None:
    """Time ``codes`` in ``rounds`` interleaved rounds and print CPU s per ``unit``, per
    arcmin^2 (``area``) and against SWarp, with the load average after each round."""
    times: dict[str, list[float]] = {name: [] for name in codes}
    load = []
    for _ in range(rounds):
        for name, run in codes.items():
            child, start = child_cpu(), time.process_time()
            run()
            times[name].append(time.process_time() - start + child_cpu() - child)
        load.append(os.getloadavg()[0])
    medians = {name: float(np.median(values)) for name, values in times.items()}
    reference = medians.get("SWarp LANCZOS3 weighted")
    rows = [
        (
            name,
            seconds,
            1e3 * seconds / area,
            f"{seconds / reference:.2f}" if reference else "-",
        )
        for name, seconds in medians.items()
    ]
    header = ["code", f"CPU s / {unit}", "CPU ms / arcmin^2", "/ SWarp"]
    print(format_table(header, rows, ["s", ".3f", ".1f", "s"]))
    print(f"\nload average (1 min) after each round: {', '.join(f'{v:.2f}' for v in load)}\n")


def peer_codes(
    exposures: list[Exposure], wcs: WCS, shape: tuple[int, int], work: Path
) -> dict[str, Callable[[], object]]:
    """The other codes resampling ``exposures`` onto the grid (``wcs``, ``shape``)."""
    codes: dict[str, Callable[[], object]] = {
        "scipy + astropy (order 3)": lambda: scipy_coadd(exposures, wcs, shape),
        "GalSim InterpolatedImage L3": lambda: galsim_coadd(exposures, wcs, shape),
    }
    try:
        import reproject  # noqa: F401

        codes["reproject_interp (bicubic)"] = lambda: reproject_coadd(exposures, wcs, shape)
    except ImportError:
        pass
    work.mkdir(exist_ok=True)
    swarp = swarp_runner(exposures, wcs, shape, work)
    if swarp is not None:
        codes["SWarp LANCZOS3 weighted"] = swarp
    return codes


#: The scipy code of the realistic job, run in a fresh process: reads the FITS files,
#: resamples them onto the grid, writes the weighted mean.
SCIPY_PROCESS = """
import json, sys
import fitsio, numpy as np
from astropy.io import fits
from astropy.wcs import WCS
from scipy import ndimage
job = json.loads(sys.argv[1])
grid = WCS(fits.Header.fromstring(job["header"], sep="\\n"))
ny, nx = job["shape"]
total = np.zeros((ny, nx))
weights = 0.0
for name in job["names"]:
    image, header = fitsio.read(name, header=True)
    weight = float(np.median(fitsio.read(name.replace(".fits", ".weight.fits"))))
    wcs = WCS(fits.Header.fromstring(str(header), sep="\\n"))
    for y0 in range(0, ny, 256):  # bands of rows: bounded memory
        yy, xx = np.mgrid[y0 : min(ny, y0 + 256), 0:nx].astype(np.float64)
        ra, dec = grid.wcs_pix2world(xx.ravel(), yy.ravel(), 0)
        x, y = wcs.wcs_world2pix(ra, dec, 0)
        warped = ndimage.map_coordinates(image, [y, x], order=3, mode="constant")
        total[y0 : y0 + yy.shape[0]] += weight * warped.reshape(yy.shape)
    weights += weight
fitsio.write(job["out"], (total / weights).astype(np.float32), clobber=True)
"""


def child_runner(command: list[str], env: dict[str, str] | None = None) -> Callable[[], object]:
    """A function running ``command`` to completion (its CPU lands in RUSAGE_CHILDREN)."""

    def run() -> None:
        result = subprocess.run(command, capture_output=True, text=True, env=env, check=False)
        if result.returncode != 0:
            raise RuntimeError(f"{command[:3]} failed:\n{result.stderr[-3000:]}")

    return run


class StageClock:
    """CPU time (``time.process_time``) by stage, exclusive: functions wrapped by
    :meth:`wrap` charge their time to their stage, minus that of wrapped functions they
    call (charged to those). Undo the wrapping with :meth:`restore`."""

    def __init__(self) -> None:
        self.totals: dict[str, float] = {}
        self._stack: list[list] = []
        self._undo: list[tuple[object, str, object]] = []

    def wrap(self, owner: object, attribute: str, stage: str) -> None:
        original = getattr(owner, attribute)
        clock = self

        def timed(*args, **kwargs):  # type: ignore[no-untyped-def]
            return clock.run(stage, original, *args, **kwargs)

        self._undo.append((owner, attribute, original))
        setattr(owner, attribute, timed)

    def run(self, stage: str, function, *args, **kwargs):  # type: ignore[no-untyped-def]
        now = time.process_time()
        if self._stack:
            parent = self._stack[-1]
            self.totals[parent[0]] = self.totals.get(parent[0], 0.0) + now - parent[1]
        self._stack.append([stage, now])
        try:
            return function(*args, **kwargs)
        finally:
            end = time.process_time()
            name, start = self._stack.pop()
            self.totals[name] = self.totals.get(name, 0.0) + end - start
            if self._stack:
                self._stack[-1][1] = end

    def restore(self) -> None:
        for owner, attribute, original in reversed(self._undo):
            setattr(owner, attribute, original)
        self._undo.clear()


def stage_profile(
    paths: list[str], patch, n_noise: int, out: Path
) -> tuple[dict[str, float], float]:  # type: ignore[no-untyped-def]
    """CPU s by stage of one serial ``cellcoadd build`` of ``patch`` in this process (as the
    command does it: headers, build, write), and the total."""
    import cellcoadd.builder.cell as cell_module
    import cellcoadd.builder.cell_sums as sums_module
    import cellcoadd.builder.exposure_planes as planes_module
    import cellcoadd.builder.inputs as inputs_module
    import cellcoadd.builder.mapping as mapping_module
    from cellcoadd.io.api import write
    from cellcoadd.io.exposures.exposure_source import ExposureFile
    from cellcoadd.model.sources import describe

    clock = StageClock()
    wrapped = [
        (inputs_module.BuildInput, "load", "header and read"),
        (inputs_module, "exposure_frame", "mapping"),
        (mapping_module._Deferred, "evaluate", "mapping"),
        (cell_module, "select_exposure", "selection"),
        (planes_module, "input_planes", "input planes + noise generation"),
        (planes_module, "interpolate_bad_pixels", "mask interpolation"),
        (sums_module, "draw_exposure_psf", "PSF draw"),
        (sums_module, "warp_planes", "PSF warp"),
        (cell_module, "psf_moments", "PSF moments"),
        (cell_module, "accumulate_warped", "warp kernel"),
        (cell_module, "warp_mask_or", "warp kernel (mask)"),
        (sums_module.BlockSums, "add", "accumulation"),
        (cell_module, "finish_cell", "finishing"),
    ]
    for owner, attribute, stage in wrapped:
        clock.wrap(owner, attribute, stage)
    try:
        start = time.process_time()
        sources = clock.run("header and read", lambda: [describe(ExposureFile(p)) for p in paths])
        coadd = clock.run(
            "other build",
            lambda: build_patch(patch, sources, BuildConfig(n_noise=n_noise), 1, progress=False),
        )
        clock.run("write", lambda: write(coadd, out, overwrite=True))
        total = time.process_time() - start
    finally:
        clock.restore()
    return clock.totals, total


def realistic_job(args: argparse.Namespace, work: Path) -> None:
    """The LSST patch from FITS exposure files, whole process: cellcoadd build, SWarp, scipy."""
    from cellcoadd.io.exposures.exposure_io import write_exposure

    config = SkyMapConfig(
        pixel_scale=PIXEL_SCALE,
        cell_inner=150,
        cell_border=50,
        cells_per_patch=args.cells_per_patch,
        patches_per_tract=3,
    )
    skymap = SkyMap.from_centers([CENTER], config)
    tract = skymap[0]
    patch = tract.patch(1, 1)
    wcs, shape = grid_wcs(patch)
    ra, dec = wcs.wcs_pix2world([[(shape[1] - 1) / 2, (shape[0] - 1) / 2]], 0)[0]
    n_cells = len(patch.cells)
    area = shape[0] * shape[1] * (PIXEL_SCALE / 60.0) ** 2
    print(
        f"## realistic job: a patch of {n_cells} cells ({shape[1]} x {shape[0]} px over the "
        f"outer boxes, {area:.1f} arcmin^2) from {args.exposures} FITS exposure files of "
        f"{args.size} x {args.size} px at {EXPOSURE_SCALE} arcsec/px, whole process\n"
    )
    start = time.perf_counter()
    exposures = make_exposures(
        (float(ra), float(dec)), args.exposures, args.size, max_rotation=10.0, max_offset=10.0
    )
    paths = []
    for exposure in exposures:
        path = work / f"visit{exposure.visit:04d}.fits"
        write_exposure(exposure, path)
        paths.append(str(path))
    plain = write_plain_fits(exposures, work)
    del exposures
    (work / "skymap.json").write_text(skymap.to_json())
    print(f"inputs written in {time.perf_counter() - start:.1f} s\n")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}

    def cellcoadd_build(k: int) -> Callable[[], object]:
        command = [sys.executable, "-m", "cellcoadd", "build", *paths]
        command += ["--skymap", str(work / "skymap.json"), "--tract", str(tract.id)]
        command += ["--patch", f"{patch.index[0]},{patch.index[1]}", "--n-noise", str(k)]
        command += ["--out", str(work / f"coadd-k{k}.h5"), "--overwrite", "--quiet"]
        return child_runner(command, env)

    job = {"names": plain, "shape": list(shape), "out": str(work / "scipy.fits")}
    job["header"] = wcs.to_header().tostring(sep="\n")
    codes = {
        "cellcoadd build K=0 (+PSF)": cellcoadd_build(0),
        "cellcoadd build K=3 (+PSF)": cellcoadd_build(3),
        "scipy + astropy (order 3)": child_runner(
            [sys.executable, "-c", SCIPY_PROCESS, json.dumps(job)], env
        ),
    }
    if swarp_program() is not None:
        codes["SWarp LANCZOS3 weighted"] = swarp_files_runner(plain, wcs, shape, work)
    compare(codes, args.rounds, area, "patch")
    for k in args.stages_noise if args.stages else ():
        totals, total = stage_profile(paths, patch, k, work / "stages.h5")
        rows = [
            (stage, seconds, 100 * seconds / total)
            for stage, seconds in sorted(totals.items(), key=lambda item: -item[1])
        ]
        print(
            f"cellcoadd K={k} CPU by stage (one serial build in this process, {total:.1f} CPU "
            f"s; load average {os.getloadavg()[0]:.2f}):\n"
        )
        print(format_table(["stage", "CPU s", "%"], rows, ["s", ".2f", ".1f"]))
        print()


def small_job(args: argparse.Namespace, work: Path) -> None:
    """Today's 36-cell patch from in-memory exposures, then one cell alone."""
    config = SkyMapConfig(
        pixel_scale=PIXEL_SCALE,
        cell_inner=150,
        cell_border=50,
        cells_per_patch=4,
        patches_per_tract=3,
    )
    tract = SkyMap.from_centers([CENTER], config)[0]
    patch = tract.patch(1, 1)
    wcs, shape = grid_wcs(patch)
    ra, dec = wcs.wcs_pix2world([[(shape[1] - 1) / 2, (shape[0] - 1) / 2]], 0)[0]
    exposures = make_exposures((float(ra), float(dec)), args.small_exposures, args.small_size)
    area = shape[0] * shape[1] * (PIXEL_SCALE / 60.0) ** 2  # arcmin^2
    n_cells = len(list(patch.cells))
    cell = patch.cells[len(patch.cells) // 2 + 2]  # an inner cell
    cell_shape = cell.outer_bbox.shape
    cell_area = cell_shape[0] * cell_shape[1] * (PIXEL_SCALE / 60.0) ** 2
    print(
        f"## small job: a patch of {n_cells} cells (grid {shape[1]} x {shape[0]} px, "
        f"{area:.1f} arcmin^2) from {args.small_exposures} in-memory exposures of "
        f"{args.small_size} x {args.small_size} px (inputs hold many times the grid's pixels)"
    )
    try:
        import reproject  # noqa: F401
    except ImportError:
        print("reproject is not installed: skipped")

    def cellcoadd_patch(k: int) -> Callable[[], object]:
        build = BuildConfig(n_noise=k)
        return lambda: build_patch(patch, exposures, build, seed=1, progress=False)

    def cellcoadd_cell(k: int) -> Callable[[], object]:
        build = BuildConfig(n_noise=k)
        return lambda: build_cell(cell, exposures, build, seed=1)

    codes = {
        "cellcoadd K=0 (+PSF)": cellcoadd_patch(0),
        "cellcoadd K=3 (+PSF)": cellcoadd_patch(3),
        **peer_codes(exposures, wcs, shape, work / "patch"),
    }
    codes["cellcoadd K=0 (+PSF)"]()  # warm-up: numba kernels, imports
    print(
        f"\nthe patch: cellcoadd builds its {n_cells} cells (outer boxes, overlapping), "
        f"the others one {shape[1]} x {shape[0]} grid\n"
    )
    compare(codes, args.rounds, area, "patch")
    codes = {
        "cellcoadd K=0 (+PSF)": cellcoadd_cell(0),
        "cellcoadd K=3 (+PSF)": cellcoadd_cell(3),
        **peer_codes(exposures, cell.wcs, cell_shape, work / "cell"),
    }
    print(
        f"one cell {cell.index}: its {cell_shape[1]} x {cell_shape[0]} outer box "
        f"({cell_area:.2f} arcmin^2) for every code\n"
    )
    compare(codes, args.rounds, cell_area, "cell")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--cells-per-patch", type=int, default=20, help="realistic job")
    parser.add_argument("--exposures", type=int, default=6, help="realistic job")
    parser.add_argument("--size", type=int, default=3800, help="realistic exposure side, px")
    parser.add_argument("--small-exposures", type=int, default=4)
    parser.add_argument("--small-size", type=int, default=2000, help="small-job exposure side")
    parser.add_argument("--no-small", dest="small", action="store_false", help="skip job 2")
    parser.add_argument("--no-stages", dest="stages", action="store_false", help="no stages")
    parser.add_argument(
        "--stages-noise",
        type=lambda text: [int(k) for k in text.split(",")],
        default=[3],
        help="noise realizations K of the stage profiles, comma-separated (default 3)",
    )
    parser.add_argument("--workdir", help="where the inputs go (default: a temporary dir)")
    args = parser.parse_args()
    print(f"peers: {machine_summary()}")
    print(f"CPU vector extensions: {cpu_features()}; load average {os.getloadavg()}")
    print(f"medians of {args.rounds} interleaved rounds, one core each")
    if swarp_program() is None:
        print("SWarp is not installed (apt-get install swarp): skipped")
    print()
    if args.workdir:
        Path(args.workdir).mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=args.workdir) as directory:
        realistic_job(args, Path(directory))
        if args.small:
            small_job(args, Path(directory))


if __name__ == "__main__":
    main()
