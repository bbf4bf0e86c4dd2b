"""How far from a cell's centre its one PSF stamp still describes the coadd PSF.

The coadd PSF at a position is that of a cell shifted there (the same tract pixels, the
same inputs): this builds cell (0, 0) and copies of it moved by ``d`` coadd pixels (along
x, and diagonally), and prints the adaptive-moments size and shape of each coadd PSF
against the centre's: ``dT/T`` and ``de1, de2`` (distortions) against ``d``.

Two kinds of inputs, 6 exposures each (0.263"/pixel, rotations and sub-pixel offsets
varied, all covering every moved cell):

* ``sim``: the simulator's focal-plane variation (``cellcoadd simulate --psf-variation``:
  FWHM +5% and a radial shear |g| = 0.01 at the corner of a DECam-sized focal plane, radius
  15000 pixels), the cell at 80% of the corner radius from the boresight in a different
  direction per exposure (the focal plane's outer CCDs, where the gradients are largest);
* ``psfex``: the real DECam PSFEx model of ``tests/data/des`` (exposure 154912,
  CCD 12), the cell centre at CCD pixels (1024 + 150 k, 2048 - 300 k) for exposure k;
* ``constant``: the same Moffat everywhere: what resampling alone does (each position
  meets the exposures' pixels at another sub-pixel phase), the floor of the others.

Then (``stars``, the table of ``BuildConfig.psf_phase``) unit-flux stars injected at the
centre, edges and corners of a cell's inner box and at random positions, into 6 rotated
0.263"/px exposures of the simulator's PSF (the steep variation of ``tests/test_psf_phase.py``
on a Moffat of FWHM 0.9") and of the DECam PSFEx model, each star's coadded image against
``cell.psf`` (old: the centre), ``psf_at`` with the corners alone (old) and ``psf_at``
with the corners and the phase terms (new), and with the phase terms alone; and the CPU
time of one ``psf_at``.

Usage::

    .venv/bin/python benchmarks/psf_across_cell.py            # ~2 CPU minutes
    .venv/bin/python benchmarks/psf_across_cell.py stars      # the star table only
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
import warnings
from pathlib import Path

import galsim
import numpy as np
from astropy.wcs import WCS

from cellcoadd import BuildConfig, Exposure, SkyMap, SkyMapConfig, build_cell
from cellcoadd.builder.cell_sums import cell_jacobian
from cellcoadd.builder.psf import psf_moments
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.tract import Cell
from cellcoadd.io import read_psfex
from cellcoadd.sim.psf import focal_plane_psf

#: The real DECam CCD of the tests (GalSim's test data, BSD-3-Clause), in the repository.
DES_DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "des"
PSFEX_FILE = DES_DATA / "DECam_00154912_12_psfcat.psf"
SCALE = 0.263
CORNER = 15000.0
DISTANCES = (0, 15, 30, 45, 60, 75)
CONFIG = SkyMapConfig(cell_inner=150, cell_border=50, cells_per_patch=1, patches_per_tract=1)


def _wcs(ra: float, dec: float, x: float, y: float, angle: float) -> WCS:
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = [ra, dec]
    wcs.wcs.crpix = [x + 1.0, y + 1.0]
    c, s = math.cos(angle), math.sin(angle)
    wcs.wcs.cd = np.array([[-c, s], [s, c]]) * SCALE / 3600.0
    wcs.wcs.set()
    return wcs


def exposures(kind: str, ra: float, dec: float) -> list[Exposure]:
    size = 500
    out = []
    for k in range(6):
        centre = (size / 2 + 0.3 * k, size / 2 - 0.2 * k)
        wcs = _wcs(ra, dec, *centre, angle=math.radians(23.0 * k))
        if kind == "constant":
            psf, origin = galsim.Moffat(beta=3.5, fwhm=0.9), (0, 0)
        elif kind == "sim":
            phi = 2.0 * math.pi * k / 6
            boresight = (
                centre[0] - 0.8 * CORNER * math.cos(phi),
                centre[1] - 0.8 * CORNER * math.sin(phi),
            )
            base = galsim.Moffat(beta=3.5, fwhm=0.9)
            psf = focal_plane_psf(base, boresight, CORNER, 0.05, 0.01)
            origin = (0, 0)
        else:
            psf = read_psfex(PSFEX_FILE)
            origin = (int(1024 + 150 * k - size / 2), int(2048 - 300 * k - size / 2))
        out.append(
            Exposure(
                image=np.zeros((size, size)),
                wcs=wcs,
                variance=1.0,
                psf=psf,
                visit=k,
                detector=12,
                band="r",
                zero_point=30.0,
                origin=origin,
            )  # fmt: skip
        )
    return out


def profile(kind: str) -> list[tuple[str, int, float, float, float]]:
    tract = SkyMap.from_centers([(60.0, -30.0)], CONFIG)[0]
    cell = tract.cell(0, 0)
    inputs = exposures(kind, *cell.center_sky)
    config = BuildConfig(n_noise=0, psf_size=75)
    jacobian = cell_jacobian(cell)
    rows = []
    centre = None
    for direction, (ux, uy) in (("x", (1, 0)), ("diagonal", (1, 1))):
        for d in DISTANCES:
            step = (round(d * ux / math.hypot(ux, uy)), round(d * uy / math.hypot(ux, uy)))
            moved = dataclasses.replace(
                cell,
                inner_bbox=cell.inner_bbox.shifted(*step),
                outer_bbox=cell.outer_bbox.shifted(*step),
            )
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                coadd = build_cell(moved, inputs, config)
            assert coadd.n_used == len(inputs), coadd.inputs
            m = psf_moments(coadd.psf, jacobian)
            if centre is None:
                centre = m
            distance = math.hypot(*step)
            rows.append(
                (
                    direction,
                    int(round(distance)),
                    m["psf_T"] / centre["psf_T"] - 1.0,
                    m["psf_e1"] - centre["psf_e1"],
                    m["psf_e2"] - centre["psf_e2"],
                )
            )
    return rows


def model_profile(kind: str) -> list[tuple[int, float, float, float, float, float, float]]:
    """The PSF models alone: each exposure's PSF drawn at the cell centre and ``d`` coadd
    pixels away along x, moved by a whole number of exposure pixels (the same sub-pixel
    phase, so no resampling enters): the mean over the exposures (what their coadd sees)
    and the largest single exposure's (a coadd of one pointing)."""
    tract = SkyMap.from_centers([(60.0, -30.0)], CONFIG)[0]
    inputs = exposures(kind, *tract.cell(0, 0).center_sky)
    rows = []
    for d in DISTANCES:
        step = round(d * 0.2 / SCALE)
        values = []
        for e in inputs:
            found = []
            for x in (250.0, 250.0 + step):
                box = Box(x_start=int(x) - 24, x_stop=int(x) + 25, y_start=226, y_stop=275)
                stamp = e.draw_psf(x, 250.0, box)
                found.append(psf_moments(stamp, e.local_jacobian(x, 250.0)))
            values.append(
                (
                    found[1]["psf_T"] / found[0]["psf_T"] - 1.0,
                    found[1]["psf_e1"] - found[0]["psf_e1"],
                    found[1]["psf_e2"] - found[0]["psf_e2"],
                )
            )
        mean = np.mean(values, axis=0)
        worst = np.max(np.abs(values), axis=0)
        rows.append((d, *(float(v) for v in mean), *(float(v) for v in worst)))
    return rows


#: Star positions, cell array pixels (inner box 50..199, centre 125), at least 48 px apart.
FIXED = [("centre", (125, 125)), ("edge +x", (199, 125)), ("edge -y", (125, 50)),
         ("edge -x", (50, 140)), ("corner ++", (199, 199)), ("corner --", (50, 50)),
         ("corner +-", (199, 50)), ("between", (150, 180)), ("between", (80, 100))]  # fmt: skip
HALF = 25


def _star_exposures(kind: str, cell: Cell, stars: list[tuple[int, int]]) -> list[Exposure]:
    out = []
    for k in range(6):
        centre = (250.0 + 0.3 * k, 250.0 - 0.2 * k)
        wcs = _wcs(*cell.center_sky, *centre, angle=math.radians(23.0 * k))
        if kind == "sim":
            phi = 0.3 * k
            boresight = (250.0 - 800.0 * math.cos(phi), 250.0 - 800.0 * math.sin(phi))
            psf = focal_plane_psf(galsim.Moffat(beta=3.5, fwhm=0.9), boresight, 1000.0, 0.05, 0.01)
            origin = (0, 0)
        else:
            psf = read_psfex(PSFEX_FILE)
            origin = (1024 + 150 * k - 250, 2048 - 300 * k - 250)
        common = dict(wcs=wcs, variance=1.0, psf=psf, visit=k, detector=12, band="r",
                      zero_point=30.0, origin=origin)  # fmt: skip
        blank = Exposure(image=np.zeros((500, 500)), **common)
        image = np.zeros((500, 500))
        for x, y in stars:
            sky = cell.wcs.pixel_to_world_values(x, y)
            ex, ey = (float(v) for v in wcs.world_to_pixel_values(*sky))
            box = Box(x_start=int(ex) - 30, x_stop=int(ex) + 31, y_start=int(ey) - 30,
                      y_stop=int(ey) + 31)  # fmt: skip
            image[box.slices] += blank.draw_psf(ex, ey, box)
        out.append(Exposure(image=image, **common))
    return out


def _separated(rng: np.random.Generator, n: int) -> list[tuple[int, int]]:
    """``n`` random pixels of the inner box at least 55 px apart."""
    picked: list[tuple[int, int]] = []
    while len(picked) < n:
        x, y = (int(v) for v in rng.integers(50, 200, size=2))
        if all(math.hypot(x - a, y - b) >= 55 for a, b in picked):
            picked.append((x, y))
    return picked


def star_table(kind: str, n_random: int = 24) -> None:
    """Print, per star, |dT/T| and |de| = max(|de1|, |de2|) of the centre stamp, of psf_at
    with corners only (old), with corners and phase terms (new), with phase terms only."""
    tract = SkyMap.from_centers([(60.0, -30.0)], CONFIG)[0]
    cell = tract.cell(0, 0)
    jacobian = cell_jacobian(cell)
    rng = np.random.default_rng(7)
    groups = [[xy for _, xy in FIXED]] + [_separated(rng, 4) for _ in range(n_random // 4)]
    names = [name for name, _ in FIXED] + ["random"] * (4 * (n_random // 4))
    variants = {"centre psf": (True, False), "psf_at old": (True, False),
                "psf_at new": (True, True), "phase only": (False, True)}  # fmt: skip
    rows: list[list[tuple[float, float]]] = []
    cost = []
    for stars in groups:
        inputs = _star_exposures(kind, cell, stars)
        built = {}
        for corners, phase in set(variants.values()):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                config = BuildConfig(n_noise=0, psf_size=2 * HALF + 1, psf_corners=corners,
                                     psf_phase=phase)  # fmt: skip
                built[(corners, phase)] = build_cell(cell, inputs, config)
        for x, y in stars:
            cut = built[(True, True)].image[y - HALF : y + HALF + 1, x - HALF : x + HALF + 1]
            star = psf_moments(cut.astype(np.float64) / cut.sum(), jacobian)
            row = []
            for name, key in variants.items():
                coadd = built[key]
                if name == "centre psf":
                    stamp = coadd.psf
                else:
                    start = time.process_time()
                    stamp = coadd.psf_at(x, y)
                    if name == "psf_at new":
                        cost.append(time.process_time() - start)
                m = psf_moments(stamp, jacobian)
                de = max(abs(m["psf_e1"] - star["psf_e1"]), abs(m["psf_e2"] - star["psf_e2"]))
                row.append((m["psf_T"] / star["psf_T"] - 1.0, de))
            rows.append(row)
    print(f"{kind}: stars against the PSF served (dT/T, max |de1|, |de2|); 6 rotated inputs")
    print("  position     (x, y)    " + "".join(f"{name:>22}" for name in variants))
    positions = [xy for group in groups for xy in group]
    for name, (x, y), row in zip(names, positions, rows, strict=True):
        cells = "".join(f"  {dt:+.1e} {de:.1e}     " for dt, de in row)
        print(f"  {name:<10} ({x:3d}, {y:3d})  {cells}")
    values = np.array(rows)  # (stars, variants, 2)
    random = values[len(FIXED) :]
    for label, part in (("max |.| all", values), ("rms random", random)):
        if label.startswith("max"):
            stats = np.abs(part).max(axis=0)
        else:
            stats = np.sqrt(np.mean(part**2, axis=0))
        print(f"  {label:<23}" + "".join(f"  {t:.1e} {e:.1e}        " for t, e in stats))
    print(f"  psf_at (corners + phase, 6 inputs, 51-px stamp): {1e3 * np.median(cost):.1f} ms CPU")


def main() -> None:
    if sys.argv[1:] == ["stars"]:
        for kind in ("sim", "psfex"):
            star_table(kind)
        return
    for kind in ("sim", "psfex"):
        star_table(kind)
    for kind in ("constant", "sim", "psfex"):
        print(f'{kind}, coadd PSF of moved cells: d (coadd px at 0.2"), dT/T, de1, de2')
        for direction, d, dT, de1, de2 in profile(kind):
            print(f"  {direction:<8} {d:3d}  {dT:+.2e}  {de1:+.2e}  {de2:+.2e}")
        if kind != "constant":
            print(f"{kind}, the input models alone (same phase): mean; largest |.| of one")
            for d, dT, de1, de2, wT, w1, w2 in model_profile(kind):
                print(
                    f"  x        {d:3d}  {dT:+.2e}  {de1:+.2e}  {de2:+.2e};"
                    f"  {wT:.2e}  {w1:.2e}  {w2:.2e}"
                )


if __name__ == "__main__":
    main()
