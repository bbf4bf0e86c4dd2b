"""The committed JSON Schemas in ``schemas/`` match the metadata models."""

from __future__ import annotations

import json
from pathlib import Path

from cellcoadd.model.patch_coadd import FORMAT_VERSION
from cellcoadd.model.schemas import SCHEMA_MODELS, schema_documents, write_schemas

COMMITTED = Path(__file__).resolve().parents[1] / "schemas"
HINT = "schemas are out of date: run `cellcoadd schemas --out schemas/`"


def test_committed_schemas_are_current(tmp_path):
    written = write_schemas(tmp_path)
    major = FORMAT_VERSION.split(".")[0]
    assert sorted(p.name for p in written) == sorted(f"{n}.v{major}.json" for n in SCHEMA_MODELS)
    for fresh in written:
        committed = COMMITTED / fresh.name
        assert committed.exists(), f"{committed} is missing; {HINT}"
        assert committed.read_bytes() == fresh.read_bytes(), f"{committed} differs; {HINT}"
    stale = {p.name for p in COMMITTED.glob("*.json")} - {p.name for p in written}
    assert not stale, f"stale schema files {sorted(stale)}; {HINT}"


def test_schema_text_is_stable_and_describes_the_models():
    first, second = schema_documents(), schema_documents()
    assert first == second
    for name, text in first.items():
        assert text.endswith("}\n")
        schema = json.loads(text)
        assert text == json.dumps(schema, indent=2, sort_keys=True) + "\n"
        model = SCHEMA_MODELS[name.split(".")[0]]
        assert schema["title"] == model.__name__
        assert set(schema["properties"]) == set(model.model_fields)
    patch_schema = json.loads(first["PatchMetadata.v1.json"])
    assert {"skymap_config", "build_config", "mask_bits", "format_version"} <= set(
        patch_schema["required"] + list(patch_schema["properties"])
    )
    statuses = json.loads(first["InputRecord.v1.json"])["properties"]["status"]["enum"]
    assert statuses[0] == "used" and "edge" in statuses
