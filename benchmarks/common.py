"""Shared pieces of the benchmarks: timing, tables, machine description, synthetic inputs.

Timings on a shared machine are noisy, so every figure a benchmark prints is either a
median of repeated runs or a ratio against a reference measured in the same run.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Sequence
from typing import Any

import galsim
import numpy as np
from astropy.wcs import WCS

from cellcoadd.geometry.skymap import SkyMap
from cellcoadd.geometry.tract import Cell
from cellcoadd.model.exposure import Exposure

#: Where the benchmark tract sits on the sky (deg); any position away from the poles.
SKY_CENTER = (60.0, -30.0)


# --- timing -----------------------------------------------------------------------------


def median_seconds(
    function: Callable[[], Any], repeats: int, *, clock: Callable[[], float] = time.perf_counter
) -> tuple[float, Any]:
    """Median duration (s) of ``repeats`` calls of ``function`` and its last result.

    ``clock`` is ``time.perf_counter`` (wall time, default) or ``time.process_time``
    (CPU time of this process, insensitive to other load but blind to child processes).
    """
    durations = []
    result = None
    for _ in range(repeats):
        start = clock()
        result = function()
        durations.append(clock() - start)
    return float(np.median(durations)), result


def interleaved_medians(
    functions: dict[str, Callable[[], Any]],
    repeats: int,
    *,
    clock: Callable[[], float] = time.perf_counter,
) -> dict[str, float]:
    """Median duration (s) of each function; runs interleave so load drifts hit all."""
    durations: dict[str, list[float]] = {name: [] for name in functions}
    for _ in range(repeats):
        for name, function in functions.items():
            start = clock()
            function()
            durations[name].append(clock() - start)
    return {name: float(np.median(values)) for name, values in durations.items()}


# --- tables -----------------------------------------------------------------------------


def format_table(
    header: Sequence[str], rows: Sequence[Sequence[Any]], formats: Sequence[str]
) -> str:
    """Markdown table (readable as plain text too).

    ``formats`` are ``format()`` specs per column, e.g. ``".2f"`` or ``"d"``; a column
    whose spec is ``"s"`` holds text and is left-aligned, the others right-aligned.
    """
    cells = [
        [
            value if isinstance(value, str) else format(value, spec)
            for value, spec in zip(row, formats, strict=True)
        ]
        for row in rows
    ]
    widths = [
        max(len(str(title)), *(len(row[i]) for row in cells)) for i, title in enumerate(header)
    ]
    text = [spec == "s" for spec in formats]

    def line(values: Sequence[str]) -> str:
        padded = [
            value.ljust(width) if left else value.rjust(width)
            for value, width, left in zip(values, widths, text, strict=True)
        ]
        return "| " + " | ".join(padded) + " |"

    rule = "|" + "|".join(
        ":" + "-" * (width + 1) if left else "-" * (width + 1) + ":"
        for width, left in zip(widths, text, strict=True)
    )
    return "\n".join([line(header), rule + "|", *(line(row) for row in cells)])


def machine_summary() -> str:
    """One line: CPU model, cores available to this process, memory, Python version."""
    model = platform.processor() or "unknown CPU"
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    memory = "unknown memory"
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemTotal"):
                    memory = f"{int(line.split()[1]) / 1024**2:.1f} GiB RAM"
                    break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"{model}, {cores} cores, {memory}, Python {platform.python_version()}"


def idle_cores(seconds: float = 1.0) -> float:
    """How many cores sat idle over the next ``seconds`` (from ``/proc/stat``; NaN if
    unavailable): 2.0 on an idle 2-core machine, ~0 when other jobs keep both busy."""

    def totals() -> tuple[float, float, int]:
        with open("/proc/stat") as stat:
            lines = stat.read().splitlines()
        fields = [float(v) for v in lines[0].split()[1:]]
        n_cpus = sum(1 for line in lines if line.startswith("cpu") and line[3:4].isdigit())
        return fields[3] + fields[4], sum(fields[:8]), n_cpus  # idle + iowait, all

    try:
        idle0, all0, n_cpus = totals()
        time.sleep(seconds)
        idle1, all1, _ = totals()
    except (OSError, IndexError, ValueError):
        return float("nan")
    return n_cpus * (idle1 - idle0) / max(all1 - all0, 1.0)


# --- synthetic inputs -------------------------------------------------------------------


def lsst_skymap() -> SkyMap:
    """One tract with the LSST defaults (0.2"/px, cells 150 + 2 x 50 px, 20 x 20 per patch)."""
    return SkyMap.from_centers([SKY_CENTER])


def exposure_wcs(
    center: tuple[float, float], shape: tuple[int, int], pixel_scale: float, rotation_deg: float
) -> WCS:
    """TAN WCS of a ``shape`` exposure whose central pixel is ``center`` (deg), rotated."""
    ny, nx = shape
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = list(center)
    wcs.wcs.crpix = [(nx - 1) / 2 + 1, (ny - 1) / 2 + 1]
    theta = np.radians(rotation_deg)
    rotation = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    scale = pixel_scale / 3600.0
    wcs.wcs.cd = np.array([[-scale, 0.0], [0.0, scale]]) @ rotation
    wcs.wcs.set()
    return wcs


def covering_exposures(
    cell: Cell,
    n_exposures: int,
    seed: int,
    *,
    pixel_scale: float = 0.26,
    size: int = 360,
    max_offset_arcsec: float = 5.0,
) -> list[Exposure]:
    """``n_exposures`` noise-only exposures that each cover ``cell`` whole.

    Each is ``size`` x ``size`` pixels at ``pixel_scale`` arcsec/px, centred on the cell
    centre plus a random offset of up to ``max_offset_arcsec`` per axis, rotated by a
    random angle, with a Moffat PSF (beta 3.5, FWHM 0.8-1.1 arcsec), Gaussian noise of
    variance 1-2 counts^2 and a zero point within 0.05 mag of 30. The default size covers
    the 50 arcsec outer box at any rotation and offset plus the Lanczos-3 footprint.
    """
    rng = np.random.default_rng(seed)
    ra0, dec0 = cell.center_sky
    exposures = []
    for visit in range(n_exposures):
        dx, dy = rng.uniform(-max_offset_arcsec, max_offset_arcsec, 2) / 3600.0
        center = (ra0 + dx / np.cos(np.radians(dec0)), dec0 + dy)
        wcs = exposure_wcs(center, (size, size), pixel_scale, rng.uniform(0.0, 360.0))
        variance = rng.uniform(1.0, 2.0)
        image = rng.normal(0.0, np.sqrt(variance), (size, size)).astype(np.float32)
        exposures.append(
            Exposure(
                image=image,
                wcs=wcs,
                variance=variance,
                psf=galsim.Moffat(beta=3.5, fwhm=rng.uniform(0.8, 1.1)),
                visit=visit,
                detector=0,
                band="r",
                zero_point=30.0 + rng.normal(0.0, 0.05),
            )
        )
    return exposures
