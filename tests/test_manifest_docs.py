"""docs/manifest.md: every example is valid against the JSON Schema and read by the
reader, the three forms of each survey's example agree, every field is documented, and
files named and laid out as the examples say are read through them.

The files are written here with the surveys' structure: DES ``immasked`` files with the
real DECam CCD header (``tests/data/des``), LSST ``ExposureF`` files with ``MP_*``
planes, and a generic camera's ``FLUX``/``FLAGS``/``IVAR`` file with a TAN WCS.
"""

from __future__ import annotations

import json
import re
import shutil
import sys
from pathlib import Path

import fitsio
import jsonschema
import numpy as np
import pytest
from conftest import DES_PSF
from survey_psf_factory import build_piff_model
from test_presets import write_small_des
from test_survey_readers import write_lsst

from cellcoadd.io import read_manifest, sources_from_manifest
from cellcoadd.io.exposures.mef_layout import MefLayout
from cellcoadd.model.manifest import ManifestEntry

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
DOC = (ROOT / "docs" / "manifest.md").read_text()
SCHEMA = json.loads((ROOT / "schemas" / "Manifest.v1.json").read_text())
EXAMPLES = dict(re.findall(r"<!-- manifest: (\S+) -->\n```\w+\n(.*?)```", DOC, re.DOTALL))


def test_the_examples_are_found():
    forms = {name.split(".")[1] for name in EXAMPLES}
    assert {"des.toml", "des.json", "des.csv", "lsst.toml", "lsst.json", "lsst.csv"} <= set(
        EXAMPLES
    )
    assert {"generic.toml", "generic.json"} <= set(EXAMPLES) and forms == {"toml", "json", "csv"}


def _document(name: str, text: str):
    """The example as the schema sees it: the parsed TOML/JSON, or the CSV's entries."""
    if name.endswith(".toml"):
        return tomllib.loads(text)
    if name.endswith(".json"):
        data = json.loads(text)
        return {"exposures": data} if isinstance(data, list) else data
    return None


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_example_is_valid_for_the_schema_and_the_reader(tmp_path, name):
    path = tmp_path / name
    path.write_text(EXAMPLES[name])
    manifest = read_manifest(path)
    document = _document(name, EXAMPLES[name])
    if document is None:  # CSV: what the reader made of the lines
        document = json.loads(manifest.model_dump_json(exclude_none=True))
    jsonschema.validate(document, SCHEMA)
    for entry in manifest.exposures:
        if isinstance(entry.layout, dict):
            MefLayout.model_validate(entry.layout)  # a layout table is a valid MefLayout


@pytest.mark.parametrize("survey", ["des", "lsst", "generic"])
def test_the_forms_of_an_example_agree(tmp_path, survey):
    manifests = []
    for form in ("toml", "json", "csv"):
        if f"{survey}.{form}" in EXAMPLES:
            path = tmp_path / f"{survey}.{form}"
            path.write_text(EXAMPLES[f"{survey}.{form}"])
            manifests.append(read_manifest(path))
    assert len(manifests) >= 2 and all(m == manifests[0] for m in manifests)


def test_every_field_is_documented():
    for name in ManifestEntry.model_fields:
        assert f"| `{name}` |" in DOC, name
    for name in MefLayout.model_fields:
        assert f"| `{name}` |" in DOC, name
    kinds = ("mag", "fluxmag0", "bunit", "photocalib")
    assert all(f'`"{kind}"`' in DOC for kind in kinds)


def _write(directory: Path, name: str) -> Path:
    path = directory / name
    path.write_text(EXAMPLES[name])
    return path


def test_des_example_reads_des_files(tmp_path):
    first = write_small_des(tmp_path / "D00154912_r_c12_r2369p01_immasked.fits.fz")
    write_small_des(tmp_path / "D00154913_r_c12_r2369p01_immasked.fits.fz", magzero=None)
    for stem in ("D00154912", "D00154913"):
        shutil.copy(DES_PSF, tmp_path / f"{stem}_r_c12_r2369p01_psfexcat.psf")
    shape = fitsio.read(first, ext="SCI").shape
    with fitsio.FITS(tmp_path / "D00154912_r_c12_r2369p01_bkg.fits.fz", "rw") as fits:
        fits.write(None)
        fits.write(np.full(shape, 2.5, np.float32), extname="SCI", compress="GZIP_2", qlevel=None)
    for form in ("toml", "json", "csv"):
        manifest = read_manifest(_write(tmp_path, f"des.{form}"))
        sources = sources_from_manifest(manifest, tmp_path)
        headers = [source.header() for source in sources]
        assert [h.key for h in headers] == [(154912, 12), (154912, 12)]  # the same CCD header
        assert [h.zero_point for h in headers] == [30.25, 31.52]  # MAGZERO, else the entry's
        assert "BADPIX_CRAY" in headers[0].mask_bits.bits
    with_background, without = (s.load() for s in sources)
    np.testing.assert_allclose(without.image - with_background.image, 2.5, atol=1e-5)


def test_lsst_example_reads_lsst_files(tmp_path):
    write_lsst(tmp_path / "visit_image_r_2025061100123_94.fits")
    write_lsst(tmp_path / "visit_image_r_2025061100187_94.fits", band_keyword=False)
    # the PSF files are read whole when the sources are made (the Piff one because the
    # entry trusts it), and drawn only in a build
    build_piff_model(tmp_path / "visit_image_r_2025061100123_94.piff", nx=400, ny=400)
    shutil.copy(DES_PSF, tmp_path / "visit_image_r_2025061100187_94_psfexcat.psf")
    for form in ("toml", "json", "csv"):
        sources = sources_from_manifest(read_manifest(_write(tmp_path, f"lsst.{form}")), tmp_path)
        headers = [source.header() for source in sources]
        assert [h.band for h in headers] == ["r", "r"]
        assert headers[0].zero_point == pytest.approx(28.7)  # FLUXMAG0
        assert "NO_DATA" in headers[1].mask_bits.bits


def write_generic(path: Path) -> np.ndarray:
    """A file of the generic example's layout: FLUX, FLAGS (bits 0-3), IVAR; TAN WCS."""
    ny, nx = 120, 90
    rng = np.random.default_rng(5)
    wcs = [
        {"name": "CTYPE1", "value": "RA---TAN"},
        {"name": "CTYPE2", "value": "DEC--TAN"},
        {"name": "CRVAL1", "value": 150.1},
        {"name": "CRVAL2", "value": 2.2},
        {"name": "CRPIX1", "value": 45.5},
        {"name": "CRPIX2", "value": 60.5},
        {"name": "CD1_1", "value": -0.26 / 3600},
        {"name": "CD1_2", "value": 0.0},
        {"name": "CD2_1", "value": 0.0},
        {"name": "CD2_2", "value": 0.26 / 3600},
    ]
    primary = [
        {"name": "EXPID", "value": 123},
        {"name": "CHIPID", "value": 7},
        {"name": "FILTNAME", "value": "i"},
        {"name": "PHOTZP", "value": 29.75},
    ]
    flags = np.zeros((ny, nx), np.int16)
    flags[10, 20] = 1 << 2  # a cosmic ray
    ivar = np.full((ny, nx), 0.01, np.float32)
    ivar[50:52, :] = 0.0
    with fitsio.FITS(path, "rw", clobber=True) as fits:
        fits.write(None, header=primary)
        fits.write(rng.normal(0, 10, (ny, nx)).astype(np.float32), extname="FLUX", header=wcs)
        fits.write(flags, extname="FLAGS", header=wcs)
        fits.write(ivar, extname="IVAR", header=wcs)
    return ivar


def test_generic_example_reads_its_files(tmp_path):
    ivar = write_generic(tmp_path / "exp_000123_07.fits")
    shutil.copy(DES_PSF, tmp_path / "exp_000123_07.psf")
    for form in ("toml", "json"):
        (source,) = sources_from_manifest(
            read_manifest(_write(tmp_path, f"generic.{form}")), tmp_path
        )
        header = source.header()
        assert header.key == (123, 7) and header.band == "i" and header.zero_point == 29.75
        exposure = source.load()
        bits = exposure.mask_bits
        assert exposure.mask[10, 20] == bits.value("COSMIC_RAY")
        assert np.all(exposure.mask[50:52] & bits.value("NO_WEIGHT"))
        good = ivar > 0
        np.testing.assert_allclose(exposure.variance[good], 100.0, rtol=1e-6)
