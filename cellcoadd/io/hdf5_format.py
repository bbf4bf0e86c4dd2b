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

import re
from typing import Any

import h5py
import numpy as np

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.io import format_version
from cellcoadd.io.cell_records import cell_record_json, expected_shapes, parse_cell_record
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
        _write_dataset(h5, "metadata", np.frombuffer(payload, dtype=np.uint8), compress=compress)
        cells = h5.create_group("cells")
        for cell in patch.cells.values():
            _write_cell(cells, cell, compress=compress)


def _write_cell(cells: h5py.Group, cell: CellCoadd, *, compress: bool) -> None:
    group = cells.create_group(group_name(cell.index))
    record = cell_record_json(cell).encode("ascii")
    group.attrs["cell"] = np.bytes_(record)
    group.attrs["cell_sha256"] = np.bytes_(sha256_hex(record))
    for plane, dtype in _DTYPES.items():
        _write_dataset(group, plane, getattr(cell, plane).astype(dtype, copy=False), compress)
    _write_dataset(group, "inputs", inputs_to_array(cell.inputs, ascii_only=False), compress)
    for name in (*_DTYPES, "inputs"):
        # planes share shape and dtype: the name travels with the data so that a moved or
        # swapped dataset is refused rather than read as another plane
        group[name].attrs["plane"] = np.bytes_(name)


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
        check_path_readable(path)
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
            check_format_version(self.path, version)
            digest = _attr_text(self._h5.attrs["metadata_sha256"])
        with reading_errors(self.path, "reading the metadata"):
            dataset = self._h5["metadata"]
            if dataset.ndim != 1 or not 0 < dataset.shape[0] <= MAX_METADATA_BYTES:
                raise ValueError(f"metadata dataset has shape {dataset.shape}")
            self._check_checksummed(dataset)
            payload = dataset[()].astype(np.uint8, copy=False).tobytes()
            if self.verify and digest != sha256_hex(payload):
                raise CellCoaddFormatError(self.path, "metadata SHA-256 mismatch: corrupted")
            metadata = decode_metadata(self.path, payload, version)
        with reading_errors(self.path, "listing the cells"):
            groups = {}
            for name in self._h5["cells"]:
                match = _GROUP_NAME.match(name)
                if match is None:
                    raise ValueError(f"unexpected group /cells/{name}")
                groups[(int(match.group(1)), int(match.group(2)))] = name
        return metadata, groups

    def _check_checksummed(self, dataset: h5py.Dataset) -> None:
        if self.verify and dataset.size > 0 and not dataset.fletcher32:
            raise ValueError(f"dataset {dataset.name} has no Fletcher-32 checksum")

    def _group(self, index: tuple[int, int]) -> tuple[tuple[int, int], h5py.Group]:
        key = self._check_index(index)
        with reading_errors(self.path, f"cell {key} group"):
            return key, self._h5["cells"][self._groups[key]]

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
        shapes = expected_shapes(self.metadata, identity["outer_bbox"])
        planes = {}
        for plane, dtype in _DTYPES.items():
            with reading_errors(self.path, f"cell {key} plane {plane}"):
                dataset = group[plane]
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
            dataset = group["inputs"]
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


def _attr_text(value: Any) -> str:
    if isinstance(value, (bytes, np.bytes_)):
        return bytes(value).decode("ascii")
    return str(value)
