"""Property-based fuzzing of the run ledger's rows (slow).

Random bytes, text, numbers and edited JSON in every column of a stored patch row: the
ledger names the row (file and row number) or returns a record that is a patch record of
that very row, and a run builds that patch again (the same bytes) or finds it up to
date, never ending in another exception. Run with
``pytest -m slow tests/test_hostile_ledger_fuzz.py`` (``HOSTILE_FUZZ_EXAMPLES`` sets the
examples of the fast property; the run property takes a tenth of them).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sqlite3
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from run_factory import BUILD, skymap, write_field

from cellcoadd.io.exposures.index import ExposureIndex, absolute_entry
from cellcoadd.model.manifest import ManifestEntry
from cellcoadd.pipelines.survey import run_tract
from cellcoadd.pipelines.survey.ledger import Ledger, is_current
from cellcoadd.pipelines.survey.records import PatchRecord

pytestmark = pytest.mark.slow

EXAMPLES = int(os.environ.get("HOSTILE_FUZZ_EXAMPLES", "300"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
RUN_FUZZ = settings(FUZZ, max_examples=max(EXAMPLES // 10, 5))
COLUMNS = ("band", "tract", "px", "py", "state", "record", "updated")

_scalars = st.one_of(
    st.binary(max_size=48),
    st.text(st.characters(blacklist_categories=("Cs",)), max_size=48),
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
)
_json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(allow_nan=False), st.text()),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(), inner, max_size=3),
    max_leaves=8,
)


@st.composite
def row_edits(draw: st.DrawFn) -> tuple[int, str, object]:
    """(row index 0-3, column, new value): a random value, or for ``record`` also its JSON
    with one field replaced or removed, or its text with a few bytes changed."""
    row = draw(st.integers(0, 3))
    column = draw(st.sampled_from(COLUMNS))
    kind = draw(st.sampled_from(["scalar", "field", "bytes"])) if column == "record" else "scalar"
    if kind == "scalar":
        return row, column, draw(_scalars)
    if kind == "field":
        field = draw(st.sampled_from(sorted(PatchRecord.model_fields)))
        remove = draw(st.booleans())
        value = None if remove else draw(_json_values)
        return row, column, ("field", field, remove, value)
    flips = draw(st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=4))
    return row, column, ("bytes", flips)


def _apply(ledger_path: Path, edit: tuple[int, str, object]) -> None:
    """Store the edit in the ledger (rows taken in rowid order); an edit SQLite refuses
    (a key of another row) is rejected by hypothesis."""
    row, column, value = edit
    db = sqlite3.connect(ledger_path)
    try:
        db.execute("PRAGMA ignore_check_constraints = ON")  # any text in `state`
        rowid, record = db.execute(
            "SELECT rowid, record FROM patches ORDER BY rowid LIMIT 1 OFFSET ?", (row,)
        ).fetchone()
        if isinstance(value, tuple) and value[0] == "field":
            data = json.loads(record)
            _, field, remove, new = value
            if remove:
                data.pop(field, None)
            else:
                data[field] = new
            value = json.dumps(data)
        elif isinstance(value, tuple) and value[0] == "bytes":
            raw = bytearray(record.encode())
            for offset, byte in value[1]:
                raw[offset % len(raw)] = byte
            value = bytes(raw)
        with db:
            db.execute(f"UPDATE patches SET {column} = ? WHERE rowid = ?", (value, rowid))
    except sqlite3.IntegrityError:
        assume(False)
    finally:
        db.close()


@pytest.fixture(scope="module")
def survey(tmp_path_factory) -> Path:
    """A small indexed field (one band, 2 x 2 patches) and a complete run in ``reference``."""
    root = tmp_path_factory.mktemp("ledger_fuzz")
    paths = write_field(root / "inputs", n_visits=1, patches_per_tract=2)
    with ExposureIndex(root / "inputs.sqlite") as index:
        index.update([absolute_entry(ManifestEntry(path=str(p)), ".") for p in paths])
    result = _run(root, root / "reference")
    assert len(result.built) == 4 and result.ok
    return root


def _run(root: Path, out: Path):
    return run_tract(
        root / "inputs.sqlite", skymap(2), 0, out, config=BUILD, progress=False, figure=False
    )


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@FUZZ
@given(edit=row_edits())
def test_a_damaged_ledger_row_is_named_or_read_as_its_own_patch(survey, edit):
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder)
        shutil.copy(survey / "reference" / "ledger.sqlite", out / "ledger.sqlite")
        _apply(out / "ledger.sqlite", edit)
        with Ledger(out) as ledger:
            records = ledger.records()
            for band in ("r", "x"):
                ledger.records(band, 0)
            unreadable = dict(ledger.unreadable)
        assert len(records) + len(unreadable) >= 3  # at most one row was touched
        for label, why in unreadable.items():
            assert why.startswith(f"{out / 'ledger.sqlite'}: {label} of the patches table")
        for key, record in records.items():
            assert record.key == key
            assert record.output.startswith(f"{key.band}/tract_{key.tract}/patch_")
            is_current(record, record.signature, survey / "reference", verify=True)


@RUN_FUZZ
@given(edit=row_edits())
def test_a_run_over_a_damaged_ledger_row_rebuilds_or_names_it(survey, edit):
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "out"
        shutil.copytree(survey / "reference", out)
        _apply(out / "ledger.sqlite", edit)
        result = _run(survey, out)  # never an exception: CellCoaddError or other
        assert result.ok and not result.failed, result.failed
        assert len(result.built) + len(result.up_to_date) == 4
        assert len(result.built) <= 1
        for path in sorted((survey / "reference" / "r" / "tract_0").glob("patch_*")):
            assert _sha(out / "r" / "tract_0" / path.name) == _sha(path)
        with Ledger(out) as ledger:
            records = ledger.records("r", 0)
        assert len(records) == 4 and {r.state.value for r in records.values()} == {"done"}
