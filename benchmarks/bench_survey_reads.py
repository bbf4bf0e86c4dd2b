"""What a build pays per survey exposure file: describing it, and loading a block of it.

A patch build describes every input file once (``header()``: identity, band, zero point,
mask bits, canonical WCS) and each worker then loads the part of each file its block of
cells needs (``load_described``: the header already read, so only pixels). Timed here on
a DES-layout file (``SCI``/``MSK``/``WGT``, the real DECam CCD's 255-card TPV header from
``tests/data/des``, plain and tile-compressed) and an LSST-layout file (TAN-SIP, ``MP_*``
mask bits), 2048 x 4096 px, against references measured in the same run: fitsio's
``read_header`` of the image HDU (what reading one header costs fitsio) and a plain
``load(box)`` (which parses the headers again). Interleaved rounds, medians, load average
printed.

    .venv/bin/python benchmarks/bench_survey_reads.py [--rounds 30]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import warnings
from pathlib import Path

import fitsio
import galsim
import numpy as np
from common import format_table, interleaved_medians, machine_summary

from cellcoadd.geometry.box import Box
from cellcoadd.io.exposures.mef_layout import DES_LAYOUT, LSST_LAYOUT
from cellcoadd.io.exposures.survey_readers import MefExposureFile
from cellcoadd.model.psf import GalSimPsf

#: The real DECam CCD of the tests (GalSim's test data, BSD-3-Clause), in the repository.
DES_DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "des"
NY, NX = 4096, 2048
#: A block of cells' cutout (as in a patch build: 2 x 4 cells of 250 px with borders).
BOX = Box(x_start=600, x_stop=1300, y_start=1500, y_stop=1900)
_STRUCTURAL = ("SIMPLE", "BITPIX", "EXTEND", "XTENSION", "PCOUNT", "GCOUNT", "CHECKSUM")


def des_cards() -> list[dict]:
    """The real DECam CCD header's cards, without the structural ones."""
    cards = []
    for record in fitsio.read_header(DES_DATA / "DECam_00154912_12_header.fits").records():
        name = record.get("name") or ""
        if name and name not in _STRUCTURAL and not name.startswith(("NAXIS", "Z", "DATASUM")):
            if name not in ("COMMENT", "HISTORY"):
                cards.append({"name": name, "value": record["value"]})
    return cards


def write_des(path: Path, compress: str | None) -> Path:
    rng = np.random.default_rng(1)
    image = rng.normal(0.0, 5.0, (NY, NX)).astype(np.float32)
    mask = np.zeros((NY, NX), dtype=np.int16)
    weight = np.full((NY, NX), 0.04, dtype=np.float32)
    cards = des_cards() + [{"name": "MAGZERO", "value": 31.2}]
    with fitsio.FITS(path, "rw", clobber=True) as fits:
        if compress:
            fits.write(None)
        fits.write(image, extname="SCI", header=cards, compress=compress, qlevel=None)
        fits.write(mask, extname="MSK", header=cards, compress=compress and "RICE")
        fits.write(weight, extname="WGT", header=cards, compress=compress, qlevel=None)
    return path


def write_lsst(path: Path) -> Path:
    rng = np.random.default_rng(2)
    wcs = [
        {"name": "CTYPE1", "value": "RA---TAN-SIP"},
        {"name": "CTYPE2", "value": "DEC--TAN-SIP"},
        {"name": "CRPIX1", "value": 1024.5},
        {"name": "CRPIX2", "value": 2048.5},
        {"name": "CRVAL1", "value": 150.1},
        {"name": "CRVAL2", "value": 2.2},
        {"name": "CD1_1", "value": -5.5e-5},
        {"name": "CD1_2", "value": 1.0e-6},
        {"name": "CD2_1", "value": 1.2e-6},
        {"name": "CD2_2", "value": 5.5e-5},
        {"name": "A_ORDER", "value": 2},
        {"name": "A_2_0", "value": 1.0e-7},
        {"name": "B_ORDER", "value": 2},
        {"name": "B_0_2", "value": -1.0e-7},
    ]
    planes = {"BAD": 0, "SAT": 1, "INTRP": 2, "CR": 3, "EDGE": 4, "DETECTED": 5, "NO_DATA": 8}
    primary = [
        {"name": "HIERARCH LSST BUTLER DATAID VISIT", "value": 2025061100123},
        {"name": "HIERARCH LSST BUTLER DATAID DETECTOR", "value": 94},
        {"name": "HIERARCH LSST BUTLER DATAID BAND", "value": "r"},
        {"name": "FLUXMAG0", "value": 10**11.48},
    ]
    with fitsio.FITS(path, "rw", clobber=True) as fits:
        fits.write(None, header=primary)
        fits.write(rng.normal(0, 5, (NY, NX)).astype(np.float32), extname="IMAGE", header=wcs)
        mask_cards = wcs + [{"name": f"MP_{k}", "value": v} for k, v in planes.items()]
        fits.write(np.zeros((NY, NX), np.int32), extname="MASK", header=mask_cards)
        fits.write(np.full((NY, NX), 25.0, np.float32), extname="VARIANCE", header=wcs)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=30, help="interleaved rounds")
    args = parser.parse_args()
    warnings.simplefilter("ignore")  # the real header's deprecated RADECSYS, etc.
    psf = GalSimPsf(galsim.Moffat(beta=3.5, fwhm=0.9))
    with tempfile.TemporaryDirectory() as directory:
        root = Path(directory)
        files = {
            "DES (TPV, 255 cards)": MefExposureFile(
                write_des(root / "D00154912_r_c12_immasked.fits", None), DES_LAYOUT, psf
            ),
            "DES .fits.fz": MefExposureFile(
                write_des(root / "D00154912_r_c12_immasked.fits.fz", "GZIP_2"), DES_LAYOUT, psf
            ),
            "LSST (TAN-SIP)": MefExposureFile(
                write_lsst(root / "visit_image.fits"), LSST_LAYOUT, psf
            ),
        }
        print(machine_summary())
        print(
            f"per file, ms: medians of {args.rounds} interleaved rounds; files of {NX} x {NY} px;"
            f" the block cut is {BOX.nx} x {BOX.ny} px; load average (1 min) "
            f"{os.getloadavg()[0]:.2f} at start"
        )
        rows = []
        for name, source in files.items():
            header = source.header()
            image_hdu = 1 if name == "DES .fits.fz" or name.startswith("LSST") else 0

            def fitsio_header(path: str = source.path, hdu: int = image_hdu) -> object:
                with fitsio.FITS(path) as fits:
                    return fits[hdu].read_header()

            times = interleaved_medians(
                {
                    "fitsio": fitsio_header,
                    "header": source.header,
                    "load": lambda source=source: source.load(BOX),
                    "described": lambda s=source, h=header: s.load_described(h, BOX),
                },
                args.rounds,
            )
            ms = {key: 1e3 * value for key, value in times.items()}
            rows.append(
                (name, ms["fitsio"], ms["header"], ms["load"], ms["described"],
                 ms["described"] / ms["load"])
            )  # fmt: skip
        print()
        print(
            format_table(
                [
                    "file",
                    "fitsio read_header",
                    "header()",
                    "load(box)",
                    "load_described",
                    "described / load",
                ],
                rows,
                ["s", ".2f", ".2f", ".2f", ".2f", ".2f"],
            )  # fmt: skip
        )
        print(f"\nload average (1 min) at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
