"""Property-based fuzzing of manifests, build configurations and survey headers (slow).

Each property: whatever the document or header, the reader returns a valid object or
raises the library's own error naming the file; never another exception, never a hang.
Run with ``pytest -m slow tests/test_hostile_fuzz.py``.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import fitsio
import galsim
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_survey_readers import LSST_PLANES, write_lsst

from cellcoadd.errors import CellCoaddFormatError, ConfigError
from cellcoadd.io import read_build_config, read_lsst_exposure, read_manifest
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.manifest import Manifest
from cellcoadd.model.psf import GalSimPsf

pytestmark = pytest.mark.slow

FUZZ = settings(
    max_examples=int(os.environ.get("HOSTILE_FUZZ_EXAMPLES", "300")),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
)
json_values = st.recursive(
    scalars,
    lambda children: st.one_of(
        st.lists(children, max_size=4),
        st.dictionaries(st.text(max_size=12), children, max_size=5),
    ),
    max_leaves=30,
)
entry_keys = st.sampled_from(
    [
        "path",
        "layout",
        "psf",
        "background",
        "zero_point",
        "visit",
        "detector",
        "band",
        "trust_psf",
        "extra",
    ]
)
entries = st.dictionaries(entry_keys, json_values, max_size=6)
manifests = st.one_of(
    json_values,
    st.fixed_dictionaries({"exposures": st.lists(entries, max_size=4)}),
    st.lists(entries, max_size=4),
)


def _workdir() -> Path:
    return Path(tempfile.mkdtemp(prefix="hostile-fuzz-"))


@FUZZ
@given(document=manifests)
def test_json_manifests_read_or_are_refused(document):
    directory = _workdir()
    try:
        path = directory / "m.json"
        path.write_text(json.dumps(document, allow_nan=True))
        try:
            manifest = read_manifest(path)
        except CellCoaddFormatError as err:
            assert "m.json" in str(err)
            return
        assert isinstance(manifest, Manifest) and manifest.exposures
        for entry in manifest.exposures:
            assert entry.path and (entry.zero_point is None or math.isfinite(entry.zero_point))
    finally:
        shutil.rmtree(directory)


@FUZZ
@given(text=st.text(max_size=400), kind=st.sampled_from(["toml", "csv", "json"]))
def test_text_manifests_read_or_are_refused(text, kind):
    directory = _workdir()
    try:
        path = directory / f"m.{kind}"
        path.write_text(text, encoding="utf-8")
        try:
            assert isinstance(read_manifest(path), Manifest)
        except CellCoaddFormatError as err:
            assert f"m.{kind}" in str(err)
    finally:
        shutil.rmtree(directory)


@FUZZ
@given(
    document=st.dictionaries(
        st.sampled_from([*BuildConfig.model_fields, "unknown"]), json_values, max_size=6
    )
)
def test_build_configs_read_or_are_refused(document):
    directory = _workdir()
    try:
        path = directory / "c.json"
        path.write_text(json.dumps(document, allow_nan=True))
        try:
            assert isinstance(read_build_config(path), BuildConfig)
        except (CellCoaddFormatError, ConfigError) as err:
            assert "c.json" in str(err)
    finally:
        shutil.rmtree(directory)


# -- survey headers -----------------------------------------------------------------------------

header_values = st.one_of(
    st.booleans(),
    st.integers(min_value=-(2**62), max_value=2**62),
    st.floats(allow_nan=False, allow_infinity=False, width=64),
    st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=30),
)
#: (HDU, keyword) pairs the LSST reader interprets
HEADER_TARGETS = [
    (0, "FLUXMAG0"),
    (0, "FILTER"),
    (0, "HIERARCH LSST BUTLER DATAID VISIT"),
    (0, "HIERARCH LSST BUTLER DATAID DETECTOR"),
    (0, "HIERARCH LSST BUTLER DATAID BAND"),
    (1, "CRPIX1"),
    (1, "CRVAL2"),
    (1, "CD1_1"),
    (1, "CTYPE1"),
    (1, "A_ORDER"),
    (1, "BUNIT"),
    (2, "MP_SAT"),
    (2, "MP_EDGE"),
    (2, "MP_BAD"),
]


@pytest.fixture(scope="module")
def lsst_bytes(tmp_path_factory) -> bytes:
    return write_lsst(tmp_path_factory.mktemp("fuzz") / "visit.fits").read_bytes()


@FUZZ
@given(
    edits=st.lists(
        st.tuples(st.sampled_from(HEADER_TARGETS), header_values), min_size=1, max_size=4
    )
)
def test_survey_headers_read_or_are_refused(lsst_bytes, edits):
    directory = _workdir()
    try:
        path = directory / "visit.fits"
        path.write_bytes(lsst_bytes)
        with fitsio.FITS(str(path), "rw") as fits:
            for (hdu, key), value in edits:
                fits[hdu].write_key(key.replace("HIERARCH ", ""), value)
        psf = GalSimPsf(galsim.Gaussian(sigma=0.4))
        try:
            exposure = read_lsst_exposure(path, psf, zero_point=30.0)
        except CellCoaddFormatError as err:
            assert "visit.fits" in str(err)
            return
        # what was read is what the (edited) header says, or refused above
        zero_points = [v for (h, k), v in edits if (h, k) == (0, "FLUXMAG0")]
        if zero_points:
            value = zero_points[-1]
            assert isinstance(value, (int, float)) and not isinstance(value, bool)
            assert math.isclose(exposure.zero_point, 2.5 * math.log10(value))
        edited = {k for (h, k), _ in edits if h == 2}
        for name, bit in LSST_PLANES.items():  # mask planes not edited keep their bits
            if f"MP_{name}" not in edited:
                assert exposure.mask_bits.bits[name] == bit
    finally:
        shutil.rmtree(directory)
