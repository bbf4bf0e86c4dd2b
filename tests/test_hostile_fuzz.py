"""Property-based fuzzing of manifests, build configurations, survey headers and exposure
index rows (slow).

Each property: whatever the document, header or row, the reader returns a valid object or
raises the library's own error naming the file (the row); never another exception, never
a hang.
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
import numpy as np
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


# -- exposure index rows ------------------------------------------------------------------

#: Every column of a stored index row (``id`` included: text that SQLite takes as an
#: integer moves the row away from its footprint pixels).
INDEX_COLUMNS = (
    "id", "path", "status", "reason", "entry", "layout", "psf", "visit", "detector", "band",
    "zero_point", "nx", "ny", "valid_box", "corners", "area_deg2", "header", "files", "size",
    "mtime_ns", "sha256", "indexed", "header_sha256", "n_pixels", "checksum",
)  # fmt: skip
index_values = st.one_of(
    st.binary(max_size=40),
    st.text(max_size=40),
    st.sampled_from(['{"a": 1', "[1, 2", "[[1, 2]]", "null", "[]", "{}", "NaN", "7", "1e400"]),
    json_values.map(json.dumps),
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
)


@pytest.fixture(scope="module")
def indexed_field(tmp_path_factory):
    """An index of 9 exposures (one damaged per example, in a copy) and what its rows
    hold as decoded."""
    from run_factory import skymap, write_field

    from cellcoadd.io.exposures.index import ExposureIndex, absolute_entry
    from cellcoadd.model.manifest import ManifestEntry

    root = tmp_path_factory.mktemp("index-fuzz")
    paths = write_field(root / "inputs", n_visits=1)
    entries = [absolute_entry(ManifestEntry(path=str(p)), ".") for p in paths]
    with ExposureIndex(root / "inputs.sqlite") as index:
        index.update(entries, checksum=True)
    tract = skymap()[0]
    box = tract.bbox
    x = [box.x_start - 0.5, box.x_stop - 0.5, box.x_stop - 0.5, box.x_start - 0.5]
    y = [box.y_start - 0.5, box.y_start - 0.5, box.y_stop - 0.5, box.y_stop - 0.5]
    corners = np.column_stack(tract.pixel_to_sky(np.array(x), np.array(y)))
    with ExposureIndex(root / "inputs.sqlite", readonly=True) as index:
        rows = index.by_ids([row.id for row in index.query(corners)])
        decoded = {row.path: _decoded(row) for row in rows}
    return root / "inputs.sqlite", entries, corners, decoded


def _decoded(row) -> tuple:
    """What the reads of a row give: identity, band, footprint, files, entry, header."""
    files = [(f.path, f.size, f.mtime_ns) for f in row.files]  # SHA-256s: as indexed
    return (
        row.visit, row.detector, row.band, row.corners.tolist(), files, row.entry,
        row.header_json,
    )  # fmt: skip


def _read_everything(db: Path, corners: np.ndarray, deep: set) -> dict:
    """Every read a run makes of the index's rows (query, rows by id, each decoded
    column; for rows of ``deep`` ids, and the check against the file), by path."""
    from cellcoadd.io.exposures.index import ExposureIndex

    with ExposureIndex(db, readonly=True) as index:
        rows = index.by_ids([row.id for row in index.query(corners)])
    out = {}
    for row in rows:
        out[row.path] = _decoded(row)
        row.header()
        if row.id in deep:
            assert row.not_as_indexed(str(db)) is None
            row.cross_check()
    return out


@FUZZ
@given(
    column=st.sampled_from(INDEX_COLUMNS),
    value=index_values,
    target=st.integers(min_value=0, max_value=8),
    forge=st.booleans(),
)
def test_index_rows_read_or_name_the_row(indexed_field, column, value, target, forge):
    """Whatever is written into a column of a stored row, with its checksum left alone or
    made to agree: the reads give the rows as indexed, or an IndexRowError naming the row
    (its id, or the id it had); never another exception, never other data; and indexing
    again (``--checksum`` for a consistent forgery) repairs it."""
    import sqlite3

    from cellcoadd.errors import IndexRowError
    from cellcoadd.io._files.stamps import json_sha256
    from cellcoadd.io.exposures.index import CHECKED_FIELDS, ExposureIndex, row_checksum

    template, entries, corners, decoded = indexed_field
    directory = _workdir()
    try:
        db = directory / "inputs.sqlite"
        shutil.copyfile(template, db)
        raw = sqlite3.connect(db)
        raw.row_factory = sqlite3.Row
        ids = [row[0] for row in raw.execute("SELECT id FROM exposures ORDER BY id")]
        row_id = ids[target % len(ids)]
        try:
            with raw:
                raw.execute(f"UPDATE exposures SET {column} = ? WHERE id = ?", (value, row_id))
                if column == "id":
                    row_id = value  # where the row is now; its pixels name the old id
                if forge:
                    row = raw.execute("SELECT * FROM exposures WHERE id = ?", (row_id,)).fetchone()
                    if column == "header" and isinstance(value, str):
                        sha = json_sha256(value)
                        raw.execute(
                            "UPDATE exposures SET header_sha256 = ? WHERE id = ?", (sha, row_id)
                        )
                        row = raw.execute(
                            "SELECT * FROM exposures WHERE id = ?", (row_id,)
                        ).fetchone()
                    checksum = row_checksum({name: row[name] for name in CHECKED_FIELDS})
                    raw.execute(
                        "UPDATE exposures SET checksum = ? WHERE id = ?", (checksum, row_id)
                    )
        except (sqlite3.IntegrityError, sqlite3.InterfaceError, OverflowError, TypeError):
            return  # SQLite refused the value (CHECK, NOT NULL, UNIQUE, a rowid's type)
        finally:
            raw.close()
        old_id = ids[target % len(ids)]
        try:  # a consistent forgery is found by the check against the file
            read = _read_everything(db, corners, deep={row_id} if forge else set())
        except IndexRowError as err:
            assert err.row in (old_id, row_id), (err.row, old_id, row_id, str(err))
            assert f"row {err.row}" in str(err) or f"rows [{err.row}" in str(err), str(err)
        else:
            assert read == decoded  # the column changed nothing a read uses
        if column == "id":
            return  # a moved row id is named, not repaired: index into a new file
        with ExposureIndex(db) as index:
            update = index.update(entries, checksum=forge)
            # a row whose path was damaged: its file is added again, the row marked bad
            assert len(update.added) <= (column == "path"), update
            assert len(update.bad) == len(update.added), update  # the row left: marked bad
        assert _read_everything(db, corners, deep=set()) == decoded
    finally:
        shutil.rmtree(directory)
