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

Usage::

    .venv/bin/python benchmarks/psf_across_cell.py            # ~1 CPU minute
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path

import galsim
import numpy as np
from astropy.wcs import WCS

from cellcoadd import BuildConfig, Exposure, SkyMap, SkyMapConfig, build_cell
from cellcoadd.builder.cell_sums import cell_jacobian
from cellcoadd.builder.psf import psf_moments
from cellcoadd.geometry.box import Box
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


def main() -> None:
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
