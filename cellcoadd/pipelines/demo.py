"""The end-to-end demonstration behind ``cellcoadd demo`` and ``make demo``.

Simulate a small field, build its cell coadds, store them in FITS and HDF5, read a cell
back lazily, trim the truth catalog to unique cell areas, measure shear with
metacalibration on isolated galaxies, print a report and draw the figures. What a user
looks at (coadds, catalogs, report, figures, sky map) goes directly into the output
folder; the simulated exposure files (about 4 MB each, 90 for 10 visits) are written
only when asked, into its ``exposures/`` sub-folder. The builder's numba kernels are
compiled (once, cached on disk) before the build, with a message, so the progress bar
of the build measures the build.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import galsim
import numpy as np
from astropy.table import Table

from cellcoadd.builder import build_patch
from cellcoadd.errors import CellCoaddRuntimeError
from cellcoadd.geometry import flag_unique
from cellcoadd.io import api as coadd_io
from cellcoadd.io._files.atomic import atomic_write, atomic_write_text
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.patch_coadd import PatchCoadd
from cellcoadd.pipelines.coverage import count_inputs, coverage_warning
from cellcoadd.pipelines.simulation_files import write_field_simulation
from cellcoadd.pipelines.warmup import COMPILE_TIME, kernels_cached, warm_up_kernels
from cellcoadd.shear import (
    PAPER_CUTS,
    mean_shear,
    measure_metacal,
    observation_jacobian,
    to_observation,
)
from cellcoadd.sim import DEMO_PATCH, FieldConfig, SimConfig, demo_skymap, simulate_field

DEMO_CCD_PIXELS = FieldConfig().ccd_nx  # edges cross some cells, most cells keep most visits


@dataclass
class DemoResult:
    """What the demo produced: its files (by role), the report text and key numbers."""

    out_dir: Path
    files: dict[str, Path] = field(default_factory=dict)
    report: str = ""
    numbers: dict[str, Any] = field(default_factory=dict)  # counts, floats, the cell index


class _Clock:
    """Wall-clock seconds per named step, in order."""

    def __init__(self) -> None:
        self.steps: dict[str, float] = {}
        self._start = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.steps[name] = now - self._start
        self._start = now


def _coadd_psf_fwhm(coadd: PatchCoadd) -> np.ndarray:
    """Gaussian-equivalent FWHM (arcsec) of each non-empty cell's coadd PSF."""
    scale = coadd.metadata.skymap_config.pixel_scale
    values = []
    for cell in coadd.cells.values():
        if cell.is_empty:
            continue
        moments = galsim.hsm.FindAdaptiveMom(galsim.ImageD(cell.psf), strict=False)
        values.append(2.0 * np.sqrt(2.0 * np.log(2.0)) * moments.moments_sigma * scale)
    return np.array(values)


def _trim_truth(truth: Table, skymap, coadd: PatchCoadd) -> tuple[Table, int]:
    """Truth rows of the patch with unique-area flags; checks each is kept by one cell."""
    meta = coadd.metadata
    flags = flag_unique(truth, skymap, tract=meta.tract, patch=meta.patch)
    where = skymap.locate(truth["ra"], truth["dec"])
    table = truth.copy()
    table["cell_x"], table["cell_y"] = where["cell_x"], where["cell_y"]
    for name in ("is_tract_inner", "is_patch_inner"):
        table[name] = flags[name]
    kept = np.zeros(len(table), dtype=int)
    for index in coadd.inner_cell_indices:
        cell_flags = flag_unique(truth, skymap, tract=meta.tract, cell=index)
        kept += cell_flags["is_cell_inner"]
    table["is_cell_inner"] = kept == 1
    table["is_primary"] = table["is_patch_inner"] & table["is_cell_inner"]
    if not np.array_equal(kept, flags["is_patch_inner"].astype(int)):
        raise CellCoaddRuntimeError("catalog trimming kept an object twice or lost one")
    return table, int(flags["is_patch_inner"].sum())


def _measure_shear(coadd: PatchCoadd, truth: Table, skymap) -> dict[str, float] | None:
    """Metacalibration on isolated, well-detected galaxies of the patch inner cells."""
    meta = coadd.metadata
    tract = skymap[meta.tract]
    galaxies = truth[(~truth["is_star"]) & truth["is_primary"]]
    x, y = tract.sky_to_pixel(truth["ra"], truth["dec"])
    gx, gy = tract.sky_to_pixel(galaxies["ra"], galaxies["dec"])
    half = 16  # 33 x 33 stamps (6.6 arcsec)
    results = []
    for px, py, cx, cy in zip(gx, gy, galaxies["cell_x"], galaxies["cell_y"], strict=True):
        neighbours = np.hypot(x - px, y - py)
        if np.sort(neighbours)[1] < 2.5 * half:
            continue  # keep isolated galaxies: this is not a deblender
        cell = coadd.cells[(int(cx), int(cy))]
        if cell.is_empty:
            continue
        obs = to_observation(cell)
        col = int(np.floor(px + 0.5)) - cell.outer_bbox.x_start
        row = int(np.floor(py + 0.5)) - cell.outer_bbox.y_start
        cut = (slice(row - half, row + half + 1), slice(col - half, col + half + 1))
        jacobian = observation_jacobian(obs)
        noise_sigma = float(np.sqrt(1.0 / obs["weight"].mean()))
        results.append(
            measure_metacal(
                obs["image"][cut], obs["psf"]["image"], obs["noise"][cut], jacobian, noise_sigma
            )
        )
    if len(results) < 5:
        return None
    g, g_err = mean_shear(results, selection=PAPER_CUTS, n_blocks=min(50, len(results)))
    return {"n": len(results), "g1": g[0], "g1_err": g_err[0], "g2": g[1], "g2_err": g_err[1]}


def _report(numbers: dict, coadd: PatchCoadd, fwhm: np.ndarray, clock: _Clock, files) -> str:
    counts = count_inputs(coadd)
    lines = [
        "cellcoadd demo report",
        "=====================",
        f"cells built: {numbers['cells']} ({numbers['inner_cells']} inner, "
        f"{numbers['cells'] - numbers['inner_cells']} border), {numbers['empty_cells']} empty",
        *counts.summary_lines(),
        f'coadd PSF FWHM per cell: median {np.median(fwhm):.3f}", '
        f'range {fwhm.min():.3f}-{fwhm.max():.3f}"'
        if fwhm.size
        else "no PSF (all empty)",
        f"noise: measured std of realization 0 {numbers['noise_std']:.3f}, "
        f"sqrt(median variance plane) {numbers['noise_predicted']:.3f} "
        "(resampling correlates the noise and lowers the pixel variance)",
        f"lazy read of cell {numbers['check_cell']}: identical to the built cell in FITS and HDF5",
        f"truth catalog: {numbers['objects_in_patch']} objects in the patch inner region, each "
        "kept by exactly one cell",
    ]
    if "g1" in numbers:
        lines.append(
            f"metacalibration on {numbers['shear_n']:.0f} isolated galaxies: "
            f"g1 = {numbers['g1']:.4f} +- {numbers['g1_err']:.4f} (true 0.02), "
            f"g2 = {numbers['g2']:.4f} +- {numbers['g2_err']:.4f} (true 0)"
        )
    else:
        lines.append("metacalibration: skipped (too few isolated galaxies)")
    lines.append(
        "files: "
        + ", ".join(
            f"{path.name} {path.stat().st_size / 1e6:.1f} MB"
            for role, path in files.items()
            if role.startswith("coadd")
        )
    )
    if "exposures" in files:
        lines.append(
            f"exposures: {numbers['n_exposures']} files in {files['exposures']}/ "
            f"({numbers['exposure_bytes'] / 1e6:.0f} MB); rebuild them with `cellcoadd build "
            f"{files['exposures']}/visit*.fits --skymap {files['skymap']} --tract 0 "
            f"--patch {DEMO_PATCH[0]},{DEMO_PATCH[1]} --out patch.h5`"
        )
    else:
        lines.append(
            f"exposures: {numbers['n_exposures']} simulated in memory, not written "
            "(--keep-exposures writes them)"
        )
    lines.append("timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in clock.steps.items()))
    lines.append("figures: " + ", ".join(p.name for r, p in files.items() if p.suffix == ".png"))
    return "\n".join(lines)


def run_demo(
    out_dir: str | Path,
    *,
    n_visits: int = 10,
    seed: int = 42,
    workers: int = 1,
    progress: bool = True,
    ccd_pixels: int = DEMO_CCD_PIXELS,
    keep_exposures: bool = False,
    log: Callable[[str], None] | None = None,
) -> DemoResult:
    """Run the demonstration and write everything into ``out_dir``.

    Parameters
    ----------
    out_dir : path
        Output folder (created if missing; files in it are replaced).
    n_visits : int
        Visits of the simulated 3 x 3-CCD focal plane.
    seed : int
        Seed of the simulation and of the noise realizations.
    workers : int
        Processes for building the patch.
    progress : bool
        Show progress bars.
    ccd_pixels : int
        CCD side in (0.27 arcsec) pixels.
    keep_exposures : bool
        Also write the simulated exposure files, into ``out_dir/exposures/``.
    log : callable, optional
        Receives one line per step (what is being done); default: silent.
    """
    say = log or (lambda line: None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result = DemoResult(out_dir=out)
    clock = _Clock()
    skymap = demo_skymap()
    config = SimConfig(field=FieldConfig(ccd_nx=ccd_pixels, ccd_ny=ccd_pixels))
    field_config = config.field
    say(
        f"simulating {n_visits} visits of {field_config.n_ccd_x} x {field_config.n_ccd_y} "
        f"CCDs of {ccd_pixels} x {ccd_pixels} pixels"
    )
    sim = simulate_field(config, skymap, 0, DEMO_PATCH, n_visits, seed, progress=progress)
    written = write_field_simulation(sim, out, overwrite=True, exposures=False)
    result.files["skymap"] = written[0]
    if keep_exposures:
        folder = out / "exposures"
        paths = write_field_simulation(sim, folder, overwrite=True)[: len(sim.exposures)]
        result.files["exposures"] = folder
        exposure_bytes = sum(path.stat().st_size for path in paths)
    clock.lap("simulate")
    build_config = BuildConfig()
    if kernels_cached():
        warm_up_kernels(build_config)  # loads numba's disk cache: about a second
    else:
        say(
            f"compiling the builder's numba kernels: first run only, {COMPILE_TIME}; "
            "they are cached on disk for later runs"
        )
        say(f"compiled in {warm_up_kernels(build_config):.0f} s")
    clock.lap("kernels")
    patch = skymap[0].patch(*DEMO_PATCH)
    say(f"building the {len(patch.cells)} cells of patch {DEMO_PATCH} with {workers} worker(s)")
    coadd = build_patch(
        patch, sim.exposures, build_config, seed, progress=progress, workers=workers
    )
    clock.lap("build")
    warning = coverage_warning(coadd)
    if warning:
        say(warning)
    for role, name in (("coadd_fits", "coadd.fits"), ("coadd_hdf5", "coadd.h5")):
        result.files[role] = coadd_io.write(coadd, out / name, overwrite=True)
    clock.lap("write")
    check = max(coadd.inner_cell_indices, key=lambda i: coadd.cells[i].n_used)
    for role in ("coadd_fits", "coadd_hdf5"):
        with coadd_io.open(result.files[role]) as stored:
            if not stored.read_cell(check).equals(coadd.cells[check]):
                raise CellCoaddRuntimeError(
                    f"cell {check} read from {result.files[role]} differs",
                    path=result.files[role],
                    cell=check,
                )
    clock.lap("read back")
    truth, n_in_patch = _trim_truth(sim.truth, skymap, coadd)
    result.files["truth_trimmed"] = out / "truth_trimmed.fits"

    def write_truth(temporary: Path) -> None:
        truth.write(temporary, format="fits")

    atomic_write(result.files["truth_trimmed"], write_truth, overwrite=True)
    clock.lap("trim")
    shear = _measure_shear(coadd, truth, skymap)
    clock.lap("shear")
    say("drawing the figures")
    # matplotlib is imported only here, when the figures are drawn
    from cellcoadd.plots import plot_cell_planes, plot_inputs_map, plot_patch_layout, plot_stitched

    result.files["layout"] = Path(plot_patch_layout(patch, out / "layout.png"))
    result.files["stitched"] = Path(plot_stitched(coadd, out / "stitched.png"))
    result.files["cell"] = Path(
        plot_cell_planes(
            coadd.cells[check],
            out / "cell.png",
            mask_bits=coadd.metadata.mask_bits,
            units=coadd.metadata.units,
            zero_point=coadd.metadata.zero_point,
        )
    )
    result.files["inputs"] = Path(plot_inputs_map(coadd, out / "inputs.png"))
    clock.lap("plots")
    inner = coadd.cells[check].inner
    numbers: dict[str, Any] = {
        "cells": len(coadd.cells),
        "inner_cells": len(coadd.inner_cell_indices),
        "empty_cells": len(coadd.empty_cell_indices),
        "noise_std": float(np.std(inner.noise[0])),
        "noise_predicted": float(np.sqrt(np.median(inner.variance))),
        "check_cell": check,
        "objects_in_patch": n_in_patch,
        "n_exposures": len(sim.exposures),
    }
    if keep_exposures:
        numbers["exposure_bytes"] = exposure_bytes
    if shear:
        numbers.update({"shear_n": shear["n"], **{k: v for k, v in shear.items() if k != "n"}})
    counts = count_inputs(coadd)
    numbers.update({f"records_{k}": v for k, v in counts.records.items()})
    numbers.update({f"visits_{k}": v for k, v in counts.visits.items()})
    result.report = _report(numbers, coadd, _coadd_psf_fwhm(coadd), clock, result.files)
    if warning:
        result.report += "\n" + warning
    result.numbers = numbers
    result.files["report"] = atomic_write_text(
        out / "report.txt", result.report + "\n", overwrite=True
    )
    return result
