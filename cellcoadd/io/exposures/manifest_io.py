"""Manifests (TOML, JSON or CSV lists of input exposures) and build configurations read
from files, turned into exposure sources for a build.

Manifest forms (the fields of :class:`cellcoadd.model.manifest.ManifestEntry`):

* TOML: an array of tables ``[[exposures]]``;
* JSON: ``{"exposures": [{...}, ...]}`` or a bare list of entries;
* CSV: a header line naming the fields (``path`` required), one exposure per line, empty
  cells for fields not given (a custom layout needs TOML or JSON).

Build configurations are TOML or JSON files holding the fields of
:class:`~cellcoadd.model.build_config.BuildConfig` (unknown keys are refused).
"""

from __future__ import annotations

import csv
import json
import os
import sys
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from cellcoadd.errors import CellCoaddFormatError, ConfigError
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.manifest import Manifest, ManifestEntry
from cellcoadd.model.psf import PiffPsf, PsfexPsf, PsfModel
from cellcoadd.model.sources import ExposureSource

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

_INT_FIELDS = ("visit", "detector")
_FLOAT_FIELDS = ("zero_point",)


def _load_mapping(path: Path, what: str) -> Any:
    """The TOML or JSON document in ``path``."""
    try:
        text = path.read_bytes()
    except OSError as err:
        raise CellCoaddFormatError(path, f"cannot read the {what}: {err.strerror}") from err
    try:
        if path.suffix.lower() == ".toml":
            return tomllib.loads(text.decode("utf-8"))
        if path.suffix.lower() == ".json":
            return json.loads(text)
    except (ValueError, UnicodeDecodeError) as err:  # TOMLDecodeError, JSONDecodeError
        raise CellCoaddFormatError(path, f"not a valid {what}: {err}") from err
    raise CellCoaddFormatError(path, f"a {what} must end in .toml or .json")


def read_manifest(path: str | os.PathLike[str]) -> Manifest:
    """Read a manifest (``.toml``, ``.json`` or ``.csv``).

    Raises
    ------
    CellCoaddFormatError
        Naming the file (and the entry) for anything unreadable or invalid.
    """
    path = Path(path)
    if path.suffix.lower() == ".csv":
        data: Any = {"exposures": _csv_entries(path)}
    else:
        data = _load_mapping(path, "manifest")
        if isinstance(data, list):
            data = {"exposures": data}
    try:
        return Manifest.model_validate(data)
    except ValidationError as err:
        raise CellCoaddFormatError(path, f"invalid manifest: {_one_line(err)}") from None


def _csv_entries(path: Path) -> list[dict[str, Any]]:
    try:
        with open(path, newline="", encoding="utf-8") as file:
            rows = list(csv.DictReader(file))
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise CellCoaddFormatError(path, f"cannot read the manifest: {err}") from err
    entries = []
    for line, row in enumerate(rows, start=2):
        if None in row:
            raise CellCoaddFormatError(path, f"line {line} has more cells than the header")
        entry: dict[str, Any] = {k.strip(): v.strip() for k, v in row.items() if v and v.strip()}
        try:
            for name in _INT_FIELDS:
                if name in entry:
                    entry[name] = int(entry[name])
            for name in _FLOAT_FIELDS:
                if name in entry:
                    entry[name] = float(entry[name])
        except ValueError as err:
            raise CellCoaddFormatError(path, f"line {line}: {err}") from None
        entries.append(entry)
    return entries


def read_build_config(path: str | os.PathLike[str]) -> BuildConfig:
    """Read a build configuration (``.toml`` or ``.json``) into a validated BuildConfig.

    Raises
    ------
    ConfigError
        Naming the file and the offending fields (unknown keys included).
    """
    path = Path(path)
    data = _load_mapping(path, "build configuration")
    try:
        return BuildConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(f"{path}: invalid build configuration: {_one_line(err)}") from None


def build_config_toml(config: BuildConfig) -> str:
    """``config`` as a commented TOML file to start from (what ``cellcoadd config --show``
    prints)."""
    lines = ["# cellcoadd build configuration (BuildConfig); see docs/inputs.md", ""]
    for name, field in BuildConfig.model_fields.items():
        value = getattr(config, name)
        if field.description:
            lines.append(f"# {name}: {field.description}")
        if value is None:  # TOML has no null: a field left out keeps its default
            lines.append(f"# {name} = (left out: the default)")
            continue
        lines.append(f"{name} = {json.dumps(list(value) if isinstance(value, tuple) else value)}")
    return "\n".join(lines) + "\n"


def psf_model_file(path: str | os.PathLike[str]) -> PsfModel:
    """The PSF model in a file: ``.psf`` is PSFEx, anything else Piff."""
    return PsfexPsf(path) if str(path).lower().endswith(".psf") else PiffPsf(path)


def sources_from_manifest(
    manifest: Manifest, base: str | os.PathLike[str] = "."
) -> list[ExposureSource]:
    """One exposure source per entry, relative paths taken from ``base``.

    Nothing is read here but the PSF model files; call ``header()`` on each source to
    check that the files are readable before a build.
    """
    return [_source(entry, Path(base)) for entry in manifest.exposures]


def _source(entry: ManifestEntry, base: Path) -> ExposureSource:
    from cellcoadd.io.exposures.exposure_source import ExposureFile
    from cellcoadd.io.exposures.mef_layout import DES_LAYOUT, LSST_LAYOUT, MefLayout
    from cellcoadd.io.exposures.survey_readers import MefExposureFile

    path = base / entry.path
    if entry.layout == "cellcoadd":
        return ExposureFile(path)
    if entry.psf is None:
        raise CellCoaddFormatError(path, f"the {entry.layout} layout needs a psf model file")
    layout = (
        {"lsst": LSST_LAYOUT, "des": DES_LAYOUT}[entry.layout]
        if isinstance(entry.layout, str)
        else MefLayout.model_validate(entry.layout)
    )
    return MefExposureFile(
        path,
        layout,
        psf_model_file(base / entry.psf),
        zero_point=entry.zero_point,
        background=None if entry.background is None else base / entry.background,
        visit=entry.visit,
        detector=entry.detector,
        band=entry.band,
    )


def _one_line(err: ValidationError) -> str:
    return "; ".join(
        f"{'.'.join(str(p) for p in e['loc']) or 'manifest'}: {e['msg']}" for e in err.errors()
    )
