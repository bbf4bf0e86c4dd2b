"""JSON Schemas of the metadata models, written to versioned files.

Each schema goes to ``<out_dir>/<ModelName>.v<MAJOR>.json`` where ``MAJOR`` is the major
part of :data:`~cellcoadd.model.patch_coadd.FORMAT_VERSION`. The text is stable
(``json.dumps(indent=2, sort_keys=True)`` plus a final newline) so the committed files in
``schemas/`` can be compared byte for byte with freshly generated ones. Model docstrings are
left out (field descriptions stay), so only structural changes alter a schema.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.inputs import InputRecord
from cellcoadd.model.manifest import Manifest
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.patch_coadd import FORMAT_VERSION, PatchMetadata, parse_format_version

#: The metadata models whose schemas are published, by file stem.
SCHEMA_MODELS: dict[str, type[BaseModel]] = {
    "InputRecord": InputRecord,
    "PatchMetadata": PatchMetadata,
    "SkyMapConfig": SkyMapConfig,
    "BuildConfig": BuildConfig,
    "MaskBits": MaskBits,
    "Manifest": Manifest,
}

_DRAFT = "https://json-schema.org/draft/2020-12/schema"


def schema_documents() -> dict[str, str]:
    """File name -> schema text for every model in :data:`SCHEMA_MODELS`."""
    major = parse_format_version(FORMAT_VERSION)[0]
    documents = {}
    for name, model in SCHEMA_MODELS.items():
        schema = _without_model_docstrings(model.model_json_schema())
        schema["$schema"] = _DRAFT
        schema["$comment"] = f"cellcoadd format version {FORMAT_VERSION}"
        documents[f"{name}.v{major}.json"] = json.dumps(schema, indent=2, sort_keys=True) + "\n"
    return documents


def _without_model_docstrings(schema: dict[str, Any]) -> dict[str, Any]:
    # Pydantic copies class docstrings into "description"; they are prose, not structure,
    # and would make every docstring edit a schema change. Field descriptions are kept.
    schema.pop("description", None)
    for definition in schema.get("$defs", {}).values():
        definition.pop("description", None)
    return schema


def write_schemas(out_dir: str | Path) -> list[Path]:
    """Write every schema into ``out_dir`` (created if needed); returns the paths written."""
    directory = Path(out_dir)
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for filename, text in schema_documents().items():
        path = directory / filename
        path.write_text(text, encoding="utf-8")
        written.append(path)
    return written
