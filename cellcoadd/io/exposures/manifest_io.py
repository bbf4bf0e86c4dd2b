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
import io
import json
import os
import sys
import textwrap
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from cellcoadd.errors import CellCoaddFormatError, ConfigError
from cellcoadd.io._files.path_gate import read_bytes
from cellcoadd.io.exposures.psf_files import read_psf_file
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.manifest import Manifest, ManifestEntry
from cellcoadd.model.mask_presets import MASK_PRESETS
from cellcoadd.model.sources import ExposureSource
from cellcoadd.model.units import is_njy_zero_point

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

#: Largest manifest or configuration file read (bytes).
MAX_MANIFEST_BYTES = 64 * 1024 * 1024
#: Deepest nesting of arrays and tables accepted in a manifest or configuration (a
#: manifest needs 4: document, exposures, entry, layout).
MAX_NESTING = 16

_INT_FIELDS = ("visit", "detector")
_FLOAT_FIELDS = ("zero_point",)


class _DuplicateKey(Exception):
    """A JSON object names a key twice."""


def _unique_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """``object_pairs_hook`` of json: a key named twice is refused (the last would win)."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(key)
        out[key] = value
    return out


def _check_depth(path: Path, what: str, data: Any) -> None:
    """Refuse documents nested deeper than :data:`MAX_NESTING` (iteratively: no recursion)."""
    stack = [(data, 1)]
    while stack:
        item, depth = stack.pop()
        if depth > MAX_NESTING:
            raise CellCoaddFormatError(path, f"the {what} is nested deeper than {MAX_NESTING}")
        if isinstance(item, dict):
            stack.extend((value, depth + 1) for value in item.values())
        elif isinstance(item, list):
            stack.extend((value, depth + 1) for value in item)


def _load_mapping(path: Path, what: str) -> Any:
    """The TOML or JSON document in ``path``: no key twice, nesting at most
    :data:`MAX_NESTING` deep."""
    text = read_bytes(path, what=what, max_bytes=MAX_MANIFEST_BYTES)
    suffix = path.suffix.lower()
    if suffix not in (".toml", ".json"):
        raise CellCoaddFormatError(path, f"a {what} must end in .toml or .json")
    try:
        if suffix == ".toml":  # TOML itself refuses a key defined twice
            data = tomllib.loads(text.decode("utf-8"))
        else:
            data = json.loads(text, object_pairs_hook=_unique_pairs)
    except _DuplicateKey as err:
        raise CellCoaddFormatError(path, f"the {what} names the key {err} twice") from None
    except RecursionError:
        raise CellCoaddFormatError(
            path, f"the {what} is nested too deeply to parse (at most {MAX_NESTING})"
        ) from None
    except (ValueError, UnicodeDecodeError) as err:  # TOMLDecodeError, JSONDecodeError
        raise CellCoaddFormatError(path, f"not a valid {what}: {err}") from err
    _check_depth(path, what, data)
    return data


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
    data = read_bytes(path, what="manifest", max_bytes=MAX_MANIFEST_BYTES)
    try:
        reader = csv.DictReader(io.StringIO(data.decode("utf-8"), newline=""))
        names = [name.strip() for name in reader.fieldnames or []]
        twice = sorted({name for name in names if names.count(name) > 1})
        if twice:
            raise CellCoaddFormatError(path, f"the header line names {twice} twice")
        rows = list(reader)
    except (UnicodeDecodeError, csv.Error) as err:
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


def build_config_toml(config: BuildConfig, preset: str | None = None) -> str:
    """``config`` as a commented TOML file to start from (what ``cellcoadd config --show``
    prints).

    Values are printed as a person would give them: with ``units = "nJy"`` the zero
    point (fixed at ``2.5 log10(3631e9) = 31.4000656...``) is a comment, not a value to
    edit; ``bad_mask_bits`` is the name of ``preset`` when given (its bits in a comment).

    >>> print(build_config_toml(BuildConfig.for_survey("lsst"), preset="lsst"))
    # cellcoadd build configuration (BuildConfig); see docs/inputs.md
    <BLANKLINE>
    n_noise = 3
    # psf_size: odd side of the coadd PSF stamp, px; left out: 75, or the largest odd size
    #   the cells' outer box holds
    # psf_size = (left out: the default)
    kernel = "lanczos3"
    max_mask_fraction = 0.1
    # the 'lsst' preset: ["BAD", "SAT", "CR", "EDGE", "NO_DATA"]
    bad_mask_bits = "lsst"
    optional_mask_bits = []
    # units: output pixel unit: nJy, or count (counts at zero_point)
    units = "nJy"
    # zero_point = 31.4 for nJy (fixed: 2.5 log10(3631e9)); give it with units = "count"
    # mapping_tolerance: pixels
    mapping_tolerance = 0.001
    noise_variance = "background"
    # psf_corners: also store the coadd PSF at the 4 corner pixels of each cell's inner box
    psf_corners = false
    # psf_phase: also store each used input's resampling phase term, for psf_at
    psf_phase = false
    <BLANKLINE>
    """
    lines = ["# cellcoadd build configuration (BuildConfig); see docs/inputs.md", ""]
    for name, field in BuildConfig.model_fields.items():
        value = getattr(config, name)
        if field.description and not (name == "zero_point" and config.units == "nJy"):
            lines += textwrap.wrap(
                f"{name}: {field.description}", 88, initial_indent="# ", subsequent_indent="#   "
            )
        if value is None:  # TOML has no null: a field left out keeps its default
            lines.append(f"# {name} = (left out: the default)")
            continue
        if name == "bad_mask_bits" and preset is not None:
            if MASK_PRESETS[preset] != value:
                raise ConfigError(f"bad_mask_bits {list(value)} are not the {preset!r} preset")
            lines.append(f"# the {preset!r} preset: {json.dumps(list(value))}")
            lines.append(f"{name} = {json.dumps(preset)}")
            continue
        if name == "zero_point" and config.units == "nJy" and is_njy_zero_point(value):
            lines.append(
                f'# {name} = 31.4 for nJy (fixed: 2.5 log10(3631e9)); give it with units = "count"'
            )
            continue
        lines.append(f"{name} = {json.dumps(list(value) if isinstance(value, tuple) else value)}")
    return "\n".join(lines) + "\n"


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
        return ExposureFile(path, trust_psf=entry.trust_psf)
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
        read_psf_file(base / entry.psf, trusted=entry.trust_psf),
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
