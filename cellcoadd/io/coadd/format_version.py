"""Identification and versioning of patch files: the file-kind marker, format-version
checks and the versioned metadata JSON (with its SHA-256)."""

from __future__ import annotations

import hashlib
import json
from typing import Any

from pydantic import BaseModel

from cellcoadd.errors import CellCoaddFormatError, CellCoaddValueError
from cellcoadd.model.patch_coadd import FORMAT_VERSION, PatchMetadata, parse_format_version

#: Marker identifying a cellcoadd patch file (FITS keyword CCFORMAT, HDF5 attribute).
FILE_KIND = "cellcoadd-patch"

#: Largest metadata JSON accepted, bytes (a guard against corrupted sizes).
MAX_METADATA_BYTES = 64 * 1024 * 1024


def sha256_hex(data: bytes) -> str:
    """Hex SHA-256 digest of ``data``."""
    return hashlib.sha256(data).hexdigest()


def metadata_payload(metadata: PatchMetadata) -> tuple[bytes, str]:
    """UTF-8 JSON of ``metadata`` as written, and the format version written with it.

    The writer always writes the layout of :data:`FORMAT_VERSION`, so that is the version
    recorded, whatever version ``metadata`` was read from.
    """
    stamped = metadata.model_copy(update={"format_version": FORMAT_VERSION})
    return stamped.model_dump_json().encode("utf-8"), FORMAT_VERSION


def check_format_version(path: str, version: Any) -> tuple[int, int]:
    """``(major, minor)`` of a file's version; CellCoaddFormatError unless the major is ours."""
    if isinstance(version, bytes):
        version = version.decode("ascii", errors="replace")
    try:
        major, minor = parse_format_version(str(version))
    except CellCoaddValueError as err:
        raise CellCoaddFormatError(path, str(err)) from None
    ours = parse_format_version(FORMAT_VERSION)[0]
    if major != ours:
        raise CellCoaddFormatError(
            path,
            f"format version {version} has major version {major}; this cellcoadd reads "
            f"major version {ours} only (format {FORMAT_VERSION})",
        )
    return major, minor


def decode_metadata(path: str, payload: bytes, version: str) -> PatchMetadata:
    """Parse and validate the metadata JSON of a file whose header declares ``version``.

    Fields unknown to this reader are dropped only when the file's minor version is newer
    than ours (minor versions are additive); otherwise they are an error.
    """
    _, minor = check_format_version(path, version)
    data = json.loads(payload.decode("utf-8"))
    if not isinstance(data, dict):
        raise CellCoaddFormatError(path, "metadata JSON is not an object")
    if minor > parse_format_version(FORMAT_VERSION)[1]:
        data = _drop_unknown_fields(PatchMetadata, data)
    metadata = PatchMetadata.model_validate(data)
    config = metadata.skymap_config
    outer = config.cell_inner + 2 * config.cell_border
    if metadata.psf_size > outer:
        # the builder never makes such a stamp; a reader would allocate it for every cell
        raise CellCoaddFormatError(
            path, f"psf_size {metadata.psf_size} exceeds the cells' {outer}-pixel outer box"
        )
    if metadata.format_version != version:
        raise CellCoaddFormatError(
            path,
            f"metadata says format version {metadata.format_version} but the file header "
            f"says {version}",
        )
    return metadata


def _drop_unknown_fields(model: type[BaseModel], data: dict[str, Any]) -> dict[str, Any]:
    kept = {}
    for name, value in data.items():
        field = model.model_fields.get(name)
        if field is None:
            continue
        annotation = field.annotation
        if (
            isinstance(annotation, type)
            and issubclass(annotation, BaseModel)
            and isinstance(value, dict)
        ):
            value = _drop_unknown_fields(annotation, value)
        kept[name] = value
    return kept
