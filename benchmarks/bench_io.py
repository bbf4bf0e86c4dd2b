"""Storage speed: whole-patch write and read against reading one cell, FITS and HDF5.

The job: a full LSST-default patch, 22 x 22 cells (20 x 20 inner plus one border ring) of
250 x 250 px with K = 3 noise realizations, a 35 x 35 PSF and 20 input records per cell,
synthesized directly as a :class:`~cellcoadd.model.patch_coadd.PatchCoadd` (noise-like
float planes, so lossless compression gains what it would on real coadds' noise).

For each layout (FITS and HDF5, uncompressed and lossless-compressed) it writes the patch
(``cellcoadd.io.write``, atomic, checksums), reads it back whole (``read``, checksums
verified) and reads single cells (``read_cell``: open, find the cell, read it, verify it,
close), with medians of repeated runs. Rates are in-memory megabytes of pixel data per
second. Reads come from the page cache (the file was just written), which isolates the
library's own cost from the disk. The targets: ``read_cell`` at least 50 times faster than
reading the whole patch; for HDF5, at most 10 ms and at least 300 times faster.

Before that table it compares writes with the disk: each uncompressed layout's patch write
(``cellcoadd.io.write``: atomic, checksums, fsync) against ``dd`` writing the same number of
bytes to the same directory with ``conv=fsync`` (a Python write + fsync when ``dd`` is
missing), in interleaved rounds (dd, FITS, dd, HDF5, ...), medians, with the load average.
The target: each write at least half as fast as ``dd`` in the same run.

Run as ``.venv/bin/python benchmarks/bench_io.py [--repeats N] [--dir DIR]``;
``--write-only`` runs the comparison with ``dd`` alone, ``--cells N`` takes the first N cells
of the patch (e.g. 36 for the demo's 6 x 6).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import galsim
import numpy as np
from common import format_table, lsst_skymap, machine_summary, median_seconds

import cellcoadd.io as cio
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.inputs import InputRecord
from cellcoadd.model.patch_coadd import PatchCoadd, PatchMetadata

PATCH_INDEX = (5, 5)
N_INPUTS = 20
LAYOUTS = (
    ("FITS", "patch.fits", "none"),
    ("FITS tile-compressed", "patch.fits.fz", "lossless"),
    ("HDF5", "patch.h5", "none"),
    ("HDF5 gzip", "patch-gzip.h5", "lossless"),
)


def synthetic_patch(seed: int, n_noise: int = 3, psf_size: int = 35) -> PatchCoadd:
    """A full patch of plausible cells: noise images, a few masked pixels, a Moffat PSF."""
    rng = np.random.default_rng(seed)
    tract = lsst_skymap()[0]
    patch = tract.patch(*PATCH_INDEX)
    config = BuildConfig(n_noise=n_noise, psf_size=psf_size)
    psf = galsim.Moffat(beta=3.5, fwhm=0.9).drawImage(nx=psf_size, ny=psf_size, scale=0.2).array
    psf = psf.astype(np.float64) / psf.sum()
    cells = {}
    for cell in patch.cells:
        shape = cell.outer_bbox.shape
        mask = np.zeros(shape, dtype=np.int32)
        mask[rng.integers(0, shape[0], 20), rng.integers(0, shape[1], 20)] = 1
        inputs = [
            InputRecord(
                visit=int(visit),
                detector=int(rng.integers(0, 189)),
                band="i",
                weight=float(rng.uniform(0.5, 2.0)),
                status="used",
                overlap_fraction=1.0,
                psf_fwhm=float(rng.uniform(0.7, 1.1)),
                psf_e1=float(rng.normal(0, 0.01)),
                psf_e2=float(rng.normal(0, 0.01)),
                psf_T=float(rng.uniform(0.2, 0.4)),
                zero_point=30.0,
            )
            for visit in range(N_INPUTS)
        ]
        cells[cell.index] = CellCoadd(
            image=rng.normal(0.0, 1.0, shape).astype(np.float32),
            mask=mask,
            variance=rng.uniform(0.99, 1.01, shape).astype(np.float32),
            noise=rng.normal(0.0, 1.0, (n_noise, *shape)).astype(np.float32),
            mfrac=np.zeros(shape, dtype=np.float32),
            psf=psf,
            inputs=inputs,
            tract=cell.tract,
            index=cell.index,
            inner_bbox=cell.inner_bbox,
            outer_bbox=cell.outer_bbox,
            wcs=cell.wcs,
        )
    metadata = PatchMetadata(
        skymap_config=tract.config,
        tract=tract.id,
        tract_center=tract.center,
        patch=PATCH_INDEX,
        band="i",
        units=config.units,
        zero_point=config.zero_point,
        build_config=config,
    )
    return PatchCoadd(metadata, cells)


def pixel_megabytes(cell: CellCoadd) -> float:
    """In-memory size of a cell's planes, MB."""
    planes = (cell.image, cell.mask, cell.variance, cell.noise, cell.mfrac, cell.psf)
    return sum(plane.nbytes for plane in planes) / 1e6


def dd_write(path: Path, nbytes: int) -> None:
    """Write ``nbytes`` zero bytes to ``path`` and flush them to disk (``dd conv=fsync``)."""
    megabytes = -(-nbytes // 2**20)
    if shutil.which("dd"):
        subprocess.run(
            ["dd", "if=/dev/zero", f"of={path}", "bs=1M", f"count={megabytes}", "conv=fsync"],
            check=True,
            capture_output=True,
        )
        return
    block = bytes(2**20)
    with open(path, "wb") as stream:
        for _ in range(megabytes):
            stream.write(block)
        stream.flush()
        os.fsync(stream.fileno())


def write_vs_dd(patch: PatchCoadd, directory: Path, rounds: int) -> None:
    """Print the write throughput of the uncompressed layouts next to ``dd``'s, same run."""
    layouts = {"FITS": directory / "dd-patch.fits", "HDF5": directory / "dd-patch.h5"}
    for path in layouts.values():  # warm-up, and the byte counts dd is given
        cio.write(patch, path, overwrite=True)
    sizes = {name: os.path.getsize(path) for name, path in layouts.items()}
    scratch = directory / "dd.bin"
    times: dict[str, list[float]] = {f"{kind} {name}": [] for name in layouts for kind in "wd"}
    load_before = os.getloadavg()
    for _ in range(rounds):
        for name, path in layouts.items():
            for kind in "dw":  # dd first, then the write, every round
                target = scratch if kind == "d" else path
                target.unlink(missing_ok=True)
                os.sync()  # nothing of the previous step left for this one to flush
                start = time.perf_counter()
                if kind == "d":
                    dd_write(scratch, sizes[name])
                else:
                    cio.write(patch, path)
                times[f"{kind} {name}"].append(time.perf_counter() - start)
    load_after = os.getloadavg()
    rows = []
    for name in layouts:
        write_s = float(np.median(times[f"w {name}"]))
        dd_s = float(np.median(times[f"d {name}"]))
        megabytes = sizes[name] / 1e6
        rows.append(
            (name, megabytes, write_s, megabytes / write_s, dd_s, megabytes / dd_s, dd_s / write_s)
        )
        layouts[name].unlink(missing_ok=True)
    scratch.unlink(missing_ok=True)
    print(
        f"writes against dd (same bytes, same directory, conv=fsync), {rounds} interleaved "
        f"rounds, medians; load average {load_before[0]:.2f} before, {load_after[0]:.2f} after"
    )
    header = ["layout", "file MB", "write s", "write MB/s", "dd s", "dd MB/s", "write / dd"]
    print(format_table(header, rows, ["s", ".0f", ".3f", ".0f", ".3f", ".0f", ".2f"]))
    print("target: write / dd >= 0.50\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="whole-patch writes and reads")
    parser.add_argument("--cell-reads", type=int, default=25, help="read_cell calls per layout")
    parser.add_argument("--dir", default=None, help="where to write (default: a temp dir)")
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--dd-rounds", type=int, default=5, help="rounds of writes against dd")
    parser.add_argument("--write-only", action="store_true", help="only the dd comparison")
    parser.add_argument("--cells", type=int, default=None, help="keep the first N cells")
    parser.add_argument("--patch", default=None, help="a patch file to write instead")
    args = parser.parse_args()

    start = time.perf_counter()
    patch = cio.read(args.patch) if args.patch else synthetic_patch(args.seed)
    if args.cells is not None:
        patch = PatchCoadd(patch.metadata, dict(list(patch.cells.items())[: args.cells]))
    made = time.perf_counter() - start
    indices = list(patch.cells)
    megabytes = sum(pixel_megabytes(cell) for cell in patch.cells.values())
    print(f"I/O: {len(indices)} cells, {megabytes:.0f} MB of pixels; {machine_summary()}")
    print(
        f"synthesized in {made:.1f} s; whole-patch medians of {args.repeats}, "
        f"read_cell medians of {args.cell_reads}; warm page cache\n"
    )
    rng = np.random.default_rng(args.seed)
    rows = []
    with tempfile.TemporaryDirectory(dir=args.dir) as directory:
        write_vs_dd(patch, Path(directory), args.dd_rounds)
        if args.write_only:
            return
        for name, filename, compression in LAYOUTS:
            path = Path(directory) / filename
            write_s, _ = median_seconds(
                lambda path=path, compression=compression: cio.write(
                    patch, path, compression=compression, overwrite=True
                ),
                args.repeats,
            )
            read_s, back = median_seconds(lambda path=path: cio.read(path), args.repeats)
            if not back.equals(patch):
                raise AssertionError(f"{name}: the patch read back differs from the one written")
            picks = [indices[k] for k in rng.integers(0, len(indices), args.cell_reads)]
            durations = []
            for index in picks:
                start = time.perf_counter()
                cell = cio.read_cell(path, index)
                durations.append(time.perf_counter() - start)
                if not cell.equals(patch[index]):
                    raise AssertionError(f"{name}: cell {index} read back differs")
            cell_s = float(np.median(durations))
            rows.append(
                (
                    name,
                    os.path.getsize(path) / 1e6,
                    write_s,
                    megabytes / write_s,
                    read_s,
                    megabytes / read_s,
                    1e3 * cell_s,
                    read_s / cell_s,
                )
            )
            path.unlink()
    header = [
        "layout",
        "file MB",
        "write s",
        "write MB/s",
        "read s",
        "read MB/s",
        "read_cell ms",
        "read / read_cell",
    ]
    print(format_table(header, rows, ["s", ".0f", ".2f", ".0f", ".2f", ".0f", ".1f", ".0f"]))
    print("\ntargets: read / read_cell >= 50; HDF5: read_cell <= 10 ms and >= 300x the whole read")


if __name__ == "__main__":
    main()
