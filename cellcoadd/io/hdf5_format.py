"""HDF5 layout of a patch coadd (h5py). See ``docs/format.md`` for the full description.

Root attributes identify the file (``cellcoadd_format``), its ``format_version`` and the
SHA-256 of the metadata JSON stored in the ``/metadata`` uint8 dataset. Each cell is a
group ``/cells/<cx>_<cy>`` with datasets ``image``, ``mask``, ``variance``, ``mfrac``,
``noise`` (K, ny, nx), ``psf`` and ``inputs`` (compound), and attributes ``cell`` (identity
JSON: tract, index, boxes, exact WCS) and ``cell_sha256``.

Every non-empty dataset is chunked as a single chunk (one cell's plane) with a Fletcher-32
checksum, plus shuffle + gzip with lossless compression. The file uses the HDF5 1.10 object
formats, whose metadata blocks carry their own checksums.
"""

from __future__ import annotations

import json
import re
from typing import Any

import h5py
import numpy as np

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.io import format_version
from cellcoadd.io.cell_records import (
    WcsRecords,
    cell_record_json,
    check_cell_geometry,
    expected_shapes,
    parse_cell_record,
)
from cellcoadd.io.coadd_file import CoaddFile
from cellcoadd.io.format_version import (
    FILE_KIND,
    MAX_METADATA_BYTES,
    check_format_version,
    decode_metadata,
    sha256_hex,
)
from cellcoadd.io.inputs_table import inputs_from_array, inputs_to_array
from cellcoadd.io.read_checks import check_path_readable, reading_errors
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.inputs import InputRecord
from cellcoadd.model.patch_coadd import PatchCoadd

_LIBVER = ("v110", "v110")
_GROUP_NAME = re.compile(r"^(-?\d+)_(-?\d+)$")
_DTYPES: dict[str, np.dtype] = {
    "image": np.dtype("<f4"),
    "mask": np.dtype("<i4"),
    "variance": np.dtype("<f4"),
    "mfrac": np.dtype("<f4"),
    "noise": np.dtype("<f4"),
    "psf": np.dtype("<f8"),
}
#: Objects every cell group holds, nothing else.
_CELL_OBJECTS = frozenset((*_DTYPES, "inputs"))
#: Objects of the root group.
_ROOT_OBJECTS = frozenset(("metadata", "cells"))
#: Version from which the root attribute ``contents`` lists the cells and planes.
_CONTENTS_SINCE = (1, 2)
#: Largest ratio of a dataset's bytes to the bytes it stores (deflate: about 1032:1).
_MAX_COMPRESSION = 1100


def group_name(index: tuple[int, int]) -> str:
    """Name of a cell's group inside ``/cells``, e.g. ``3_-1``."""
    return f"{index[0]}_{index[1]}"


def write_hdf5(patch: PatchCoadd, path: str, *, compress: bool) -> None:
    """Write ``patch`` to a new HDF5 file at ``path``."""
    # looked up on the module at each write, so tests can stand in for it
    payload, version = format_version.metadata_payload(patch.metadata)
    with h5py.File(path, "w", libver=_LIBVER) as h5:
        # Fixed-length byte strings are stored inside the (checksummed) object header.
        h5.attrs["cellcoadd_format"] = np.bytes_(FILE_KIND)
        h5.attrs["format_version"] = np.bytes_(version)
        h5.attrs["metadata_sha256"] = np.bytes_(sha256_hex(payload))
        # the set of cells and planes, bound to the metadata by one digest (format 1.2)
        contents = contents_json(list(patch.cells)).encode("ascii")
        h5.attrs["contents"] = np.bytes_(contents)
        h5.attrs["contents_sha256"] = np.bytes_(sha256_hex(payload + contents))
        _write_dataset(h5, "metadata", np.frombuffer(payload, dtype=np.uint8), compress=compress)
        cells = h5.create_group("cells")
        plane_attrs = patch.metadata.unit_cards()
        wcs_records = WcsRecords()
        for cell in patch.cells.values():
            _write_cell(
                cells, cell, compress=compress, plane_attrs=plane_attrs, records=wcs_records
            )


def contents_json(indices: list[tuple[int, int]]) -> str:
    """ASCII JSON of the root attribute ``contents``: the cells' group names (sorted) and
    the objects of each cell group."""
    return json.dumps(
        {"cells": sorted(group_name(index) for index in indices), "planes": sorted(_CELL_OBJECTS)},
        separators=(",", ":"),
    )


def _write_cell(
    cells: h5py.Group,
    cell: CellCoadd,
    *,
    compress: bool,
    plane_attrs: dict[str, list[tuple[str, object, str]]] | None = None,
    records: WcsRecords | None = None,
) -> None:
    group = cells.create_group(group_name(cell.index))
    record = cell_record_json(cell, records).encode("ascii")
    group.attrs["cell"] = np.bytes_(record)
    group.attrs["cell_sha256"] = np.bytes_(sha256_hex(record))
    # Each dataset is closed (its chunk written) before the next is made, and attributes
    # come last: this order decides where HDF5 puts things, hence the file's bytes.
    for plane, dtype in _DTYPES.items():
        _write_dataset(group, plane, getattr(cell, plane).astype(dtype, copy=False), compress)
    _write_dataset(group, "inputs", inputs_to_array(cell.inputs, ascii_only=False), compress)
    for name in (*_DTYPES, "inputs"):
        # planes share shape and dtype: the name travels with the data so that a moved or
        # swapped dataset is refused rather than read as another plane
        group[name].attrs["plane"] = np.bytes_(name)
    # BUNIT (+ MAGZERO) of image/noise/variance, MP_<NAME> = bit of the mask, as in FITS
    for plane, attrs in (plane_attrs or {}).items():
        for key, value, _ in attrs:
            group[plane].attrs[key] = np.bytes_(value) if isinstance(value, str) else value


def _write_dataset(group: h5py.Group, name: str, data: np.ndarray, compress: bool) -> None:
    if data.size == 0:
        # Chunks cannot be empty, and there is nothing to checksum.
        group.create_dataset(name, data=data)
        return
    options: dict[str, Any] = {"chunks": data.shape, "fletcher32": True}
    if compress:
        # Level 1: noise-dominated float planes gain < 1% from higher levels at twice the time.
        options.update(compression="gzip", compression_opts=1, shuffle=True)
    group.create_dataset(name, data=data, **options)


class Hdf5CoaddFile(CoaddFile):
    """Lazy reader of the HDF5 layout (see the module docstring)."""

    format_name = "hdf5"

    def __init__(self, path: str, *, verify: bool = True) -> None:
        self._size = check_path_readable(path)
        self.path = path
        self.verify = verify
        with reading_errors(path, "cannot open the HDF5 file"):
            self._h5 = h5py.File(path, "r")
        try:
            metadata, groups = self._read_header_part()
        except BaseException:
            self._h5.close()
            raise
        self._groups = groups
        super().__init__(path, metadata, sorted(groups))

    def _read_header_part(self) -> tuple[Any, dict[tuple[int, int], str]]:
        with reading_errors(self.path, "reading the root attributes"):
            kind = self._h5.attrs.get("cellcoadd_format")
            if isinstance(kind, bytes):
                kind = kind.decode("ascii", errors="replace")
            if kind != FILE_KIND:
                raise CellCoaddFormatError(
                    self.path, f"not a cellcoadd patch file (cellcoadd_format = {kind!r})"
                )
            version = _attr_text(self._h5.attrs["format_version"])
            file_version = check_format_version(self.path, version)
            digest = _attr_text(self._h5.attrs["metadata_sha256"])
        with reading_errors(self.path, "checking the file structure"):
            _check_members(self._h5, _ROOT_OBJECTS, exact=False)
            for name in set(self._h5) - _ROOT_OBJECTS:
                _plain_link(self._h5, name)  # newer minors may add objects: none is a link
            cells_group = _plain_link(self._h5, "cells")
            if not isinstance(cells_group, h5py.Group):
                raise ValueError("/cells is not a group")
            _single_name(cells_group)
        with reading_errors(self.path, "reading the metadata"):
            dataset = _plain_dataset(self._h5, "metadata", self._size)
            if dataset.ndim != 1 or not 0 < dataset.shape[0] <= MAX_METADATA_BYTES:
                raise ValueError(f"metadata dataset has shape {dataset.shape}")
            self._check_checksummed(dataset)
            payload = dataset[()].astype(np.uint8, copy=False).tobytes()
            if self.verify and digest != sha256_hex(payload):
                raise CellCoaddFormatError(self.path, "metadata SHA-256 mismatch: corrupted")
            metadata = decode_metadata(self.path, payload, version)
        with reading_errors(self.path, "listing the cells"):
            groups = {}
            for name in cells_group:
                match = _GROUP_NAME.match(name)
                if match is None:
                    raise ValueError(f"unexpected group /cells/{name}")
                _plain_link(cells_group, name)
                groups[(int(match.group(1)), int(match.group(2)))] = name
        if file_version >= _CONTENTS_SINCE:
            self._check_contents(payload, groups)
        return metadata, groups

    def _check_contents(self, payload: bytes, groups: dict[tuple[int, int], str]) -> None:
        """The cell groups must be exactly those of the root attribute ``contents``, whose
        digest binds it to the metadata (a deleted or added cell group is refused)."""
        with reading_errors(self.path, "reading the list of cells"):
            if "contents" not in self._h5.attrs:
                raise ValueError("the root attribute 'contents' is missing")
            contents = bytes(self._h5.attrs["contents"])
            digest = _attr_text(self._h5.attrs["contents_sha256"])
            listed = json.loads(contents)
            cells, planes = listed["cells"], listed["planes"]
        if self.verify and digest != sha256_hex(payload + contents):
            raise CellCoaddFormatError(self.path, "SHA-256 of the list of cells mismatch")
        if sorted(planes) != sorted(_CELL_OBJECTS):
            raise CellCoaddFormatError(self.path, f"unexpected cell planes {planes}")
        found = set(groups.values())
        missing, extra = sorted(set(cells) - found), sorted(found - set(cells))
        if missing or extra or len(cells) != len(set(cells)):
            raise CellCoaddFormatError(
                self.path,
                f"the cell groups differ from the file's list of {len(cells)} cells "
                f"(missing: {missing}, not listed: {extra})",
            )

    def _check_checksummed(self, dataset: h5py.Dataset) -> None:
        if self.verify and dataset.size > 0 and not dataset.fletcher32:
            raise ValueError(f"dataset {dataset.name} has no Fletcher-32 checksum")

    def _group(self, index: tuple[int, int]) -> tuple[tuple[int, int], h5py.Group]:
        key = self._check_index(index)
        with reading_errors(self.path, f"cell {key} group"):
            group = _plain_link(self._h5["cells"], self._groups[key])
            if not isinstance(group, h5py.Group):
                raise ValueError(f"{group.name} is not a group")
            _single_name(group)
            _check_members(group, _CELL_OBJECTS, exact=True)
            return key, group

    def read_cell(self, index: tuple[int, int]) -> CellCoadd:
        key, group = self._group(index)
        with reading_errors(self.path, f"cell {key} identity"):
            record = bytes(group.attrs["cell"])
            if self.verify and _attr_text(group.attrs["cell_sha256"]) != sha256_hex(record):
                raise CellCoaddFormatError(self.path, f"cell {key}: identity SHA-256 mismatch")
            identity = parse_cell_record(record)
        if identity["index"] != key or identity["tract"] != self.metadata.tract:
            raise CellCoaddFormatError(
                self.path,
                f"group {group.name} describes cell {identity['index']} of tract "
                f"{identity['tract']}",
            )
        with reading_errors(self.path, f"cell {key} identity"):
            check_cell_geometry(self.metadata, identity)
        shapes = expected_shapes(self.metadata, identity["outer_bbox"])
        planes = {}
        for plane, dtype in _DTYPES.items():
            with reading_errors(self.path, f"cell {key} plane {plane}"):
                dataset = _plain_dataset(group, plane, self._size)
                if dataset.shape != shapes[plane]:
                    raise ValueError(f"shape {dataset.shape}, expected {shapes[plane]}")
                if (dataset.dtype.kind, dataset.dtype.itemsize) != (dtype.kind, dtype.itemsize):
                    raise ValueError(f"dtype {dataset.dtype}, expected {dtype}")
                self._check_checksummed(dataset)
                if _attr_text(dataset.attrs.get("plane", b"")) != plane:
                    raise ValueError(f"dataset {dataset.name} does not hold plane {plane!r}")
                planes[plane] = dataset[()]
        inputs = self._read_inputs(key, group)
        with reading_errors(self.path, f"cell {key} contents"):
            return CellCoadd(**planes, inputs=inputs, **identity)

    def _read_inputs(self, key: tuple[int, int], group: h5py.Group) -> list[InputRecord]:
        with reading_errors(self.path, f"cell {key} inputs"):
            dataset = _plain_dataset(group, "inputs", self._size)
            if dataset.ndim != 1 or dataset.dtype.names is None:
                raise ValueError(f"inputs dataset has shape {dataset.shape}, dtype {dataset.dtype}")
            self._check_checksummed(dataset)
            return inputs_from_array(dataset[()], ascii_only=False)

    def read_cell_inputs(self, index: tuple[int, int]) -> list[InputRecord]:
        key, group = self._group(index)
        return self._read_inputs(key, group)

    def close(self) -> None:
        h5 = getattr(self, "_h5", None)
        if h5 is not None:
            h5.close()
            self._h5 = None


def _plain_link(group: h5py.Group, name: str) -> Any:
    """``group[name]``, refused unless it is a hard link to an object of this file (soft
    and external links could make a cell or plane come from elsewhere)."""
    link = group.get(name, getlink=True)
    if link is None:
        raise KeyError(f"{group.name}/{name} is missing")
    if not isinstance(link, h5py.HardLink):
        raise ValueError(f"{group.name}/{name} is a {type(link).__name__}, not an object here")
    return group[name]


def _single_name(obj: h5py.HLObject) -> None:
    """Refuse an object reachable under several names (extra hard links): another cell
    or plane would silently read the same bytes."""
    count = h5py.h5o.get_info(obj.id).rc
    if count != 1:
        raise ValueError(f"{obj.name} is linked from {count} places")


def _check_members(group: h5py.Group, expected: frozenset[str], *, exact: bool) -> None:
    names = set(group)
    missing = sorted(expected - names)
    if missing:
        raise KeyError(f"{group.name} lacks {missing}")
    if exact and names != expected:
        raise ValueError(f"{group.name} holds unexpected objects {sorted(names - expected)}")


def _plain_dataset(group: h5py.Group, name: str, file_size: int) -> h5py.Dataset:
    """``group[name]``: a contiguous or chunked dataset stored in this file, under one
    name, that really stores the bytes its shape declares (checked before reading it)."""
    dataset = _plain_link(group, name)
    if not isinstance(dataset, h5py.Dataset):
        raise ValueError(f"{dataset.name} is not a dataset")
    _single_name(dataset)
    plist = dataset.id.get_create_plist()
    layout = plist.get_layout()
    if layout not in (h5py.h5d.CONTIGUOUS, h5py.h5d.CHUNKED):
        kind = {h5py.h5d.VIRTUAL: "virtual", h5py.h5d.COMPACT: "compact"}.get(layout, layout)
        raise ValueError(f"{dataset.name} is a {kind} dataset")
    if plist.get_external_count() > 0:
        raise ValueError(f"{dataset.name} keeps its data in external files")
    declared = dataset.size * dataset.dtype.itemsize
    if declared == 0:
        return dataset
    stored = dataset.id.get_storage_size()
    if stored > file_size:
        raise ValueError(f"{dataset.name} stores {stored} bytes, more than the file's {file_size}")
    checks_only = (h5py.h5z.FILTER_FLETCHER32, h5py.h5z.FILTER_SHUFFLE)
    filtered = layout == h5py.h5d.CHUNKED and any(
        plist.get_filter(i)[0] not in checks_only for i in range(plist.get_nfilters())
    )
    limit = _MAX_COMPRESSION * stored if filtered else stored
    if stored == 0 or declared > limit:
        raise ValueError(
            f"{dataset.name} declares {dataset.shape} ({declared} bytes) but stores {stored}"
        )
    return dataset


def _attr_text(value: Any) -> str:
    if isinstance(value, (bytes, np.bytes_)):
        return bytes(value).decode("ascii")
    return str(value)
