"""cellcoadd against other resampling codes on the same patch and cell: CPU s per area.

The job: one patch of 6 x 6 cells (4 x 4 inner cells plus the border ring; cells of 150 px
inner + 2 x 50 px border at 0.2 arcsec/px) observed by ``--exposures`` noise-and-stars
exposures of ``--size`` px at 0.26 arcsec/px, rotated and dithered, each covering the patch;
then one inner cell of that patch alone (its 250 x 250 outer box, every code on that grid).
The codes, each on one core:

* ``cellcoadd`` ``build_patch`` (serial) or ``build_cell``, K = 0 and K = 3 noise
  realizations, PSF stamps included: every cell's outer box (36 x 250 x 250 px, overlapping
  borders included; each exposure is warped once over the patch), input selection,
  Lanczos-3 warp of image + noise + variance, inverse-variance weighted mean;
* SWarp (when installed: ``apt-get install swarp``; skipped with a message otherwise): the
  exposures as FITS files with weight maps, one call with a configuration written here
  (``NTHREADS 1``, ``RESAMPLING_TYPE LANCZOS3``, ``COMBINE_TYPE WEIGHTED``, no background
  subtraction) onto the patch's grid (1000 x 1000 px covering every cell's outer box);
* scipy + astropy: the same grid mapped through astropy's WCS into each exposure,
  ``scipy.ndimage.map_coordinates(order=3)``, weighted mean;
* GalSim: each exposure an ``InterpolatedImage`` with ``Lanczos(3)`` drawn onto the grid
  (``method="no_pixel"``; GalSim uses the local affine WCS at the image centre);
* ``reproject.reproject_interp`` + weighted mean, if reproject is installed.

CPU seconds are this process's (``time.process_time``) or, for SWarp, its child's
(``getrusage``), medians of ``--rounds`` interleaved rounds (every code once per round).
"per arcmin^2" divides by the sky area each code produced: the 1000 x 1000 grid (11.1
arcmin^2) for all, the union of the cells' outer boxes for cellcoadd (the same area; its
36 cells hold 2.25x as many pixels because their borders overlap). Ratios are against
SWarp in the same run. The machine line lists the CPU's vector extensions read from
``/proc/cpuinfo``.

Run as ``.venv/bin/python benchmarks/bench_peers.py [--rounds N] [--exposures N] [--size PX]``.
"""

from __future__ import annotations

import os

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import argparse  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
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


def make_exposures(patch_center: tuple[float, float], n: int, size: int) -> list[Exposure]:
    """``n`` exposures of ``size`` px with noise and a few hundred stars, all covering the patch."""
    rng = np.random.default_rng(7)
    exposures = []
    yy, xx = np.mgrid[0:size, 0:size]
    for visit in range(n):
        dx, dy = rng.uniform(-20, 20, 2) / 3600.0
        center = (patch_center[0] + dx / np.cos(np.radians(patch_center[1])), patch_center[1] + dy)
        wcs = exposure_wcs(center, (size, size), EXPOSURE_SCALE, rng.uniform(0.0, 360.0))
        image = rng.normal(0.0, 1.0, (size, size)).astype(np.float32)
        for x, y, flux in zip(
            *rng.uniform(0, size, (2, 300)), rng.uniform(20, 500, 300), strict=True
        ):
            x0, y0 = int(x), int(y)
            sl = (slice(max(y0 - 8, 0), y0 + 9), slice(max(x0 - 8, 0), x0 + 9))
            image[sl] += flux * np.exp(-((xx[sl] - x) ** 2 + (yy[sl] - y) ** 2) / (2 * 1.6**2))
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


def swarp_runner(exposures: list[Exposure], wcs: WCS, shape: tuple[int, int], work: Path):  # type: ignore[no-untyped-def]
    """A function running SWarp on ``exposures`` onto the grid (None if SWarp is missing)."""
    program = shutil.which("swarp") or shutil.which("SWarp")
    if program is None:
        return None
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--exposures", type=int, default=4)
    parser.add_argument("--size", type=int, default=2000, help="exposure side, px")
    args = parser.parse_args()

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
    exposures = make_exposures((float(ra), float(dec)), args.exposures, args.size)
    area = shape[0] * shape[1] * (PIXEL_SCALE / 60.0) ** 2  # arcmin^2
    n_cells = len(list(patch.cells))
    cell = patch.cells[len(patch.cells) // 2 + 2]  # an inner cell
    cell_shape = cell.outer_bbox.shape
    cell_area = cell_shape[0] * cell_shape[1] * (PIXEL_SCALE / 60.0) ** 2
    print(
        f"peers: a patch of {n_cells} cells (grid {shape[1]} x {shape[0]} px, {area:.1f} arcmin^2) "
        f"from {args.exposures} exposures of {args.size} x {args.size} px; {machine_summary()}"
    )
    print(f"CPU vector extensions: {cpu_features()}")
    print(f"medians of {args.rounds} interleaved rounds, one core each")
    try:
        import reproject  # noqa: F401
    except ImportError:
        print("reproject is not installed: skipped")
    if shutil.which("swarp") is None and shutil.which("SWarp") is None:
        print("SWarp is not installed (apt-get install swarp): skipped")

    def cellcoadd_patch(k: int) -> Callable[[], object]:
        build = BuildConfig(n_noise=k)
        return lambda: build_patch(patch, exposures, build, seed=1, progress=False)

    def cellcoadd_cell(k: int) -> Callable[[], object]:
        build = BuildConfig(n_noise=k)
        return lambda: build_cell(cell, exposures, build, seed=1)

    with tempfile.TemporaryDirectory() as directory:
        codes = {
            "cellcoadd K=0 (+PSF)": cellcoadd_patch(0),
            "cellcoadd K=3 (+PSF)": cellcoadd_patch(3),
            **peer_codes(exposures, wcs, shape, Path(directory) / "patch"),
        }
        codes["cellcoadd K=0 (+PSF)"]()  # warm-up: numba kernels, imports
        print(
            f"\nthe patch: cellcoadd builds its {n_cells} cells (outer boxes, overlapping), "
            f"the others one {shape[1]} x {shape[0]} grid\n"
        )
        compare(codes, args.rounds, area, "patch")
        cell_wcs = cell.wcs
        codes = {
            "cellcoadd K=0 (+PSF)": cellcoadd_cell(0),
            "cellcoadd K=3 (+PSF)": cellcoadd_cell(3),
            **peer_codes(exposures, cell_wcs, cell_shape, Path(directory) / "cell"),
        }
        print(
            f"one cell {cell.index}: its {cell_shape[1]} x {cell_shape[0]} outer box "
            f"({cell_area:.2f} arcmin^2) for every code\n"
        )
        compare(codes, args.rounds, cell_area, "cell")


if __name__ == "__main__":
    main()
