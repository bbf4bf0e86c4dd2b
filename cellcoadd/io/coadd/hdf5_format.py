"""HDF5 layout of a patch coadd (h5py). See ``docs/format.md`` for the full description.

Root attributes identify the file (``cellcoadd_format``), its ``format_version`` and the
SHA-256 of the metadata JSON stored in the ``/metadata`` uint8 dataset. Each cell is a
group ``/cells/<cx>_<cy>`` with one dataset per plane of
:data:`~cellcoadd.model.planes.PLANES` (``image``, ``mask``, ``variance``, ``mfrac``,
``noise`` (K, ny, nx), ``psf``, and ``psf_corners`` (4, n, n) when the cells have it),
``inputs`` (compound), and attributes ``cell`` (identity JSON: tract, index, boxes, exact
WCS) and ``cell_sha256``. The root attribute ``contents`` lists the objects every cell
group holds, optional planes included when stored.

Every non-empty dataset is chunked as a single chunk (one cell's plane) with a Fletcher-32
checksum, plus shuffle + gzip with lossless compression. The file uses the HDF5 1.10 object
formats, whose metadata blocks carry their own checksums.
"""

from __future__ import annotations

import itertools
import json
import re
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, NamedTuple

import h5py
import numpy as np

from cellcoadd.errors import CellCoaddFormatError, DamagedDataError, InvalidCoaddError
from cellcoadd.geometry.tract import rubin_cell_index, rubin_patch_id
from cellcoadd.io._files import parallel
from cellcoadd.io._files.read_checks import check_path_readable, reading_errors
from cellcoadd.io.coadd import format_version
from cellcoadd.io.coadd.cell_records import (
    WcsRecords,
    cell_record_json,
    check_cell_geometry,
    expected_shapes,
    parse_cell_record,
)
from cellcoadd.io.coadd.coadd_file import CoaddFile
from cellcoadd.io.coadd.empty_cells import (
    EMPTY_ATTRIBUTE,
    EMPTY_VALUE,
    empty_plane,
    planes_without_pixels,
)
from cellcoadd.io.coadd.format_version import (
    FILE_KIND,
    MAX_METADATA_BYTES,
    check_format_version,
    decode_metadata,
    sha256_hex,
)
from cellcoadd.io.coadd.hdf5_chunks import Attribute, ChunkScratch, Member, ObjectMaker
from cellcoadd.io.coadd.inputs_table import inputs_from_array, inputs_to_array
from cellcoadd.model import planes as cell_planes
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.inputs import InputRecord
from cellcoadd.model.patch_coadd import PatchCoadd, PatchMetadata, check_planes

_LIBVER = ("v110", "v110")
_GROUP_NAME = re.compile(r"^(-?\d+)_(-?\d+)$")
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
    """Write ``patch`` to a new HDF5 file at ``path``.

    Objects are made through h5py's low-level API, each uncompressed chunk written as
    HDF5 stores it (:mod:`cellcoadd.io.coadd.hdf5_chunks`). What the next cells need (chunk
    copies with their Fletcher-32, inputs tables, identity records) is made in a worker
    thread while this one makes the objects and writes (:class:`_PreparedCells`); HDF5
    itself is only called from this thread, in the same order whatever the timing, so the
    file's bytes do not depend on it.
    """
    # every cell of a patch holds the same planes (PatchCoadd checks it)
    cells = list(patch.cells.values())
    present = cells[0].plane_names if cells else cell_planes.required_plane_names()
    write_hdf5_cells(
        patch.metadata, list(patch.cells), iter(cells), path, compress=compress, present=present
    )


def write_hdf5_cells(
    metadata: PatchMetadata,
    indices: list[tuple[int, int]],
    cells: Iterator[CellCoadd],
    path: str,
    *,
    compress: bool,
    present: tuple[str, ...],
) -> None:
    """Write the patch of ``metadata`` from its ``cells`` as they come (as
    :func:`write_hdf5`): those of ``indices`` (sorted), in that order, each holding the
    planes ``present`` (names, as :attr:`CellCoadd.plane_names`), each let go once
    written (at most ``(_AHEAD + 2) * _BATCH`` are held here)."""
    # looked up on the module at each write, so tests can stand in for it
    payload, version = format_version.metadata_payload(metadata)
    with (
        ObjectMaker(compress, _LIBVER) as maker,
        h5py.File(path, "w", libver=_LIBVER) as h5,
        _PreparedCells(cells, compress, metadata.mask_bits.value("NO_DATA")) as prepared,
    ):
        # Fixed-length byte strings are stored inside the (checksummed) object header.
        contents = contents_json(indices, present).encode("ascii")
        root = [
            ("cellcoadd_format", FILE_KIND),
            ("format_version", version),
            ("metadata_sha256", sha256_hex(payload)),
            # the set of cells and planes, bound to the metadata by one digest (format 1.2)
            ("contents", contents.decode("ascii")),
            ("contents_sha256", sha256_hex(payload + contents)),
            # Rubin's ids, informative (format 1.6): the patch's, and each cell's in its group
            ("patch_id", rubin_patch_id(metadata.patch, metadata.skymap_config)),
        ]
        maker.attributes(h5.id, root)
        maker.dataset(h5.id, "metadata", np.frombuffer(payload, dtype=np.uint8))
        writer = _CellWriter(maker, maker.group(h5.id, "cells"), metadata.unit_cards(), metadata)
        count = 0
        for cell, made in prepared:
            if count >= len(indices) or cell.index != indices[count]:
                expected = indices[count] if count < len(indices) else "none"
                raise InvalidCoaddError(f"cell {cell.index} came where {expected} was expected")
            check_planes(cell, present)
            _write_cell(writer, cell, made)
            count += 1
        if count != len(indices):
            raise InvalidCoaddError(
                f"{count} cells came of the {len(indices)} announced; cell "
                f"{indices[count]} is missing"
            )


#: Cells prepared together, and batches prepared ahead of the one written (the buffers
#: hold (_AHEAD + 2) * _BATCH cells: about 42 MB for LSST-default cells with K = 3).
_BATCH = 8
_AHEAD = 1


class _Prepared(NamedTuple):
    """What writing a cell needs, made ahead (:func:`_prepare_batch`)."""

    #: The planes stored without pixels (an empty cell's, see empty_cells).
    bare: frozenset[str]
    #: Stored chunks of the non-empty planes and inputs (empty when compressed).
    chunks: dict[str, memoryview]
    #: The inputs table.
    inputs: np.ndarray
    #: The identity record (ASCII JSON).
    record: bytes


class _PreparedCells:
    """:class:`_Prepared` of the cells, cell after cell, made :data:`_BATCH` cells at a
    time, :data:`_AHEAD` batches ahead, in a worker thread when
    :data:`~cellcoadd.io._files.parallel.THREADS` allows and the file is uncompressed (the
    copies and :func:`~cellcoadd.io.coadd.hdf5_chunks.fletcher32_rows` release the GIL). A
    batch's buffers are reused once its cells are written. Use as a context manager:
    leaving it stops the worker before the buffers go."""

    def __init__(self, cells: Iterator[CellCoadd], compress: bool, no_data: int) -> None:
        self.cells = cells
        self.compress = compress
        self.no_data = no_data  # the NO_DATA bit's value
        self.records = WcsRecords()  # used by one thread at a time
        self._slots: list[_Slot] = [{} for _ in range(_AHEAD + 2)]
        self._executor: ThreadPoolExecutor | None = None

    def __enter__(self) -> _PreparedCells:
        if parallel.THREADS > 1 and not self.compress:
            self._executor = ThreadPoolExecutor(1, thread_name_prefix="cellcoadd-hdf5")
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

    def __iter__(self) -> Iterator[tuple[CellCoadd, _Prepared]]:
        # small first batches: writing starts as soon as the first cell is ready; the
        # cells are taken from their iterator here, in this thread, a batch at a time
        sizes = itertools.chain((1, 2, 4), itertools.repeat(_BATCH))
        pending: deque[tuple[list[CellCoadd], Future[list[_Prepared]]]] = deque()
        number = 0
        while True:
            while len(pending) <= _AHEAD:
                batch = list(itertools.islice(self.cells, min(next(sizes), _BATCH)))
                if not batch:
                    break
                pending.append((batch, self._submit(batch, self._slots[number % len(self._slots)])))
                number += 1
            if not pending:
                return
            batch, future = pending.popleft()
            yield from zip(batch, future.result(), strict=True)
            del batch  # written: its cells are let go

    def _submit(self, batch: list[CellCoadd], slot: _Slot) -> Future[list[_Prepared]]:
        if self._executor is not None:
            return self._executor.submit(_prepare_batch, batch, slot, self)
        done: Future[list[_Prepared]] = Future()
        done.set_result(_prepare_batch(batch, slot, self))
        return done


#: Reusable chunk buffers of a batch, by dataset (and cell number when sizes differ).
_Slot = dict[tuple[str, int], ChunkScratch]


def _prepare_batch(batch: list[CellCoadd], slot: _Slot, cells: _PreparedCells) -> list[_Prepared]:
    """What writing the cells of ``batch`` needs: their inputs tables, identity records and
    (uncompressed) the stored chunks of their non-empty datasets, made together by name."""
    inputs = [inputs_to_array(cell.inputs, ascii_only=False) for cell in batch]
    records = [cell_record_json(cell, cells.records).encode("ascii") for cell in batch]
    # a per-input plane of an empty cell has its own zero-size shape: no marker needed
    bare = [
        frozenset(n for n in planes_without_pixels(c, cells.no_data) if not _per_input(n))
        for c in batch
    ]
    chunks: list[dict[str, memoryview]] = [{} for _ in batch]
    present = batch[0].plane_names if batch else ()
    for name in () if cells.compress else (*present, cell_planes.INPUTS):
        arrays = (
            inputs
            if name == cell_planes.INPUTS
            else [
                _stored_plane(cell, cell_planes.plane(name), name in without)
                for cell, without in zip(batch, bare, strict=True)
            ]
        )
        sizes = {array.nbytes for array in arrays}
        if sizes == {0}:
            continue
        groups = [(-1, arrays)] if len(sizes) == 1 else list(enumerate([a] for a in arrays))
        for key, group in groups:  # the cells' planes share a size: made all at once
            scratch = slot.get((name, key))
            if scratch is None:
                scratch = slot[(name, key)] = ChunkScratch()
            numbers = range(len(batch)) if key < 0 else [key]
            for number, chunk in zip(numbers, scratch.chunks(group), strict=True):
                if len(chunk) > 4:  # not an empty dataset
                    chunks[number][name] = chunk
    return [_Prepared(*made) for made in zip(bare, chunks, inputs, records, strict=True)]


def contents_json(indices: list[tuple[int, int]], planes: tuple[str, ...] | None = None) -> str:
    """ASCII JSON of the root attribute ``contents``: the cells' group names (sorted) and
    the objects of each cell group (the ``planes`` they hold, default every plane's but
    the optional ones', and the inputs table)."""
    if planes is None:
        planes = cell_planes.required_plane_names()
    return json.dumps(
        {
            "cells": sorted(group_name(index) for index in indices),
            "planes": sorted((*planes, cell_planes.INPUTS)),
        },
        separators=(",", ":"),
    )


def _stored_plane(cell: CellCoadd, spec: cell_planes.PlaneSpec, bare: bool) -> np.ndarray:
    """A plane of ``cell`` as stored: C-contiguous, little-endian, the plane's dtype;
    ``bare``: no pixels, shape ``(0,)`` (an empty cell's plane, format 1.6)."""
    if bare:
        return np.zeros((0,), dtype=spec.stored_dtype)
    return np.ascontiguousarray(getattr(cell, spec.name), dtype=spec.stored_dtype)


class _CellWriter:
    """What the cell groups of one file share."""

    def __init__(
        self,
        maker: ObjectMaker,
        cells: h5py.h5g.GroupID,
        plane_attrs: dict[str, list[tuple[str, object, str]]],
        metadata: PatchMetadata,
    ) -> None:
        self.maker = maker
        self.cells = cells
        self.patch, self.skymap_config = metadata.patch, metadata.skymap_config
        # BUNIT (+ MAGZERO) of image/noise/variance, MP_<NAME> = bit of the mask, as in FITS
        self.plane_attrs = plane_attrs


def _write_cell(writer: _CellWriter, cell: CellCoadd, prepared: _Prepared) -> None:
    """The group of a cell: its planes with their attributes, the inputs, then the
    identity attributes (chunks, inputs table and record as ``prepared``)."""
    maker = writer.maker
    members: list[Member] = []
    for spec in cell_planes.PLANES:
        plane = spec.name
        if getattr(cell, plane) is None:  # an optional plane the cell lacks
            continue
        # planes share shape and dtype: the name travels with the data so that a moved or
        # swapped dataset is refused rather than read as another plane
        attributes: list[Attribute] = [("plane", plane)]
        bare = plane in prepared.bare
        if bare:
            attributes.append((EMPTY_ATTRIBUTE, EMPTY_VALUE))
        else:
            attributes += [(key, value) for key, value, _ in writer.plane_attrs.get(plane, [])]
        data = _stored_plane(cell, spec, bare)
        members.append((plane, data, attributes, prepared.chunks.get(plane)))
    # one copy of a template group (its datasets and their attributes), then the chunks
    group = maker.group_of(writer.cells, group_name(cell.index), members)
    maker.dataset(
        group,
        cell_planes.INPUTS,
        prepared.inputs,
        [("plane", cell_planes.INPUTS)],
        repeated=True,
        chunk=prepared.chunks.get(cell_planes.INPUTS),
    )
    record = prepared.record
    rubin = np.array(rubin_cell_index(cell.index, writer.patch, writer.skymap_config), "<i4")
    maker.attributes(
        group,
        [
            ("cell", record.decode("ascii")),
            ("cell_sha256", sha256_hex(record)),
            ("rubin_cell_index", rubin),
        ],
    )


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
            metadata, groups, objects = self._read_header_part()
        except BaseException:
            self._h5.close()
            raise
        self._groups = groups
        self._objects = objects
        super().__init__(path, metadata, sorted(groups))

    def _read_header_part(
        self,
    ) -> tuple[Any, dict[tuple[int, int], str], frozenset[str]]:
        """The metadata, the cell groups by index and the objects each group holds."""
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
                raise DamagedDataError("/cells is not a group", hdu="/cells")
            _single_name(cells_group)
        with reading_errors(self.path, "reading the metadata"):
            dataset = _plain_dataset(self._h5, "metadata", self._size)
            if dataset.ndim != 1 or not 0 < dataset.shape[0] <= MAX_METADATA_BYTES:
                raise DamagedDataError(
                    f"metadata dataset has shape {dataset.shape}", hdu=dataset.name
                )
            self._check_checksummed(dataset)
            payload = dataset[()].astype(np.uint8, copy=False).tobytes()
            if self.verify and digest != sha256_hex(payload):
                raise CellCoaddFormatError(self.path, "metadata SHA-256 mismatch: corrupted")
            metadata = decode_metadata(self.path, payload, version)
        with reading_errors(self.path, "listing the cells"):
            # names only (the link index of /cells): each cell's own link and objects are
            # checked when that cell is read (:meth:`_group`), so opening the file to read
            # one cell touches no other cell's objects
            groups = {}
            for name in cells_group:
                match = _GROUP_NAME.match(name)
                if match is None:
                    raise DamagedDataError(f"unexpected group /cells/{name}", hdu=f"/cells/{name}")
                groups[(int(match.group(1)), int(match.group(2)))] = name
        objects = frozenset(cell_planes.cell_objects()) - _optional_planes()
        if file_version >= _CONTENTS_SINCE:
            objects = self._check_contents(payload, groups)
        return metadata, groups, objects

    def _check_contents(self, payload: bytes, groups: dict[tuple[int, int], str]) -> frozenset[str]:
        """The cell groups must be exactly those of the root attribute ``contents``, whose
        digest binds it to the metadata (a deleted or added cell group is refused); returns
        the objects it says each cell group holds (every plane but the optional ones not
        stored, and the inputs)."""
        with reading_errors(self.path, "reading the list of cells"):
            if "contents" not in self._h5.attrs:
                raise DamagedDataError("the root attribute 'contents' is missing")
            contents = bytes(self._h5.attrs["contents"])
            digest = _attr_text(self._h5.attrs["contents_sha256"])
            listed = json.loads(contents)
            cells, planes = listed["cells"], listed["planes"]
        if self.verify and digest != sha256_hex(payload + contents):
            raise CellCoaddFormatError(self.path, "SHA-256 of the list of cells mismatch")
        required = frozenset(cell_planes.cell_objects()) - _optional_planes()
        if (
            not isinstance(planes, list)
            or not all(isinstance(name, str) for name in planes)
            or len(set(planes)) != len(planes)
            or not required <= set(planes) <= set(cell_planes.cell_objects())
        ):
            raise CellCoaddFormatError(self.path, f"unexpected cell planes {planes}")
        found = set(groups.values())
        missing, extra = sorted(set(cells) - found), sorted(found - set(cells))
        if missing or extra or len(cells) != len(set(cells)):
            raise CellCoaddFormatError(
                self.path,
                f"the cell groups differ from the file's list of {len(cells)} cells "
                f"(missing: {missing}, not listed: {extra})",
            )
        return frozenset(planes)

    def _check_checksummed(self, dataset: h5py.Dataset) -> None:
        if self.verify and dataset.size > 0 and not dataset.fletcher32:
            raise DamagedDataError(
                f"dataset {dataset.name} has no Fletcher-32 checksum", hdu=dataset.name
            )

    def _group(self, index: tuple[int, int]) -> tuple[tuple[int, int], h5py.Group]:
        key = self._check_index(index)
        with reading_errors(self.path, f"cell {key} group"):
            group = _plain_link(self._h5["cells"], self._groups[key])
            if not isinstance(group, h5py.Group):
                raise DamagedDataError(f"{group.name} is not a group", hdu=group.name)
            _single_name(group)
            _check_members(group, self._objects, exact=True)
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
        # the inputs first: the planes with a layer per used input are sized by them
        inputs = self._read_inputs(key, group)
        n_used = sum(record.is_used for record in inputs)
        shapes = expected_shapes(self.metadata, identity["outer_bbox"], n_used)
        planes: dict[str, Any] = {}  # arrays, by CellCoadd field name
        for spec in cell_planes.PLANES:
            plane, dtype = spec.name, spec.stored_dtype
            if plane not in self._objects:  # an optional plane not stored: None
                continue
            with reading_errors(self.path, f"cell {key} plane {plane}"):
                dataset = _plain_dataset(group, plane, self._size)
                if _attr_text(dataset.attrs.get(EMPTY_ATTRIBUTE, b"")) == EMPTY_VALUE:
                    # an empty cell's plane, stored without pixels (format 1.6)
                    if n_used or dataset.shape != (0,) or not _holds(dataset, plane):
                        raise DamagedDataError(
                            f"dataset {dataset.name} marked empty in a cell with data, or "
                            "not holding this plane",
                            hdu=dataset.name,
                            cell=key,
                        )
                    no_data = self.metadata.mask_bits.value("NO_DATA")
                    planes[plane] = empty_plane(spec, shapes[plane], no_data)
                    continue
                if dataset.shape != shapes[plane]:
                    raise DamagedDataError(
                        f"shape {dataset.shape}, expected {shapes[plane]}",
                        hdu=dataset.name,
                        cell=key,
                    )
                if (dataset.dtype.kind, dataset.dtype.itemsize) != (dtype.kind, dtype.itemsize):
                    raise DamagedDataError(
                        f"dtype {dataset.dtype}, expected {dtype}", hdu=dataset.name, cell=key
                    )
                self._check_checksummed(dataset)
                if not _holds(dataset, plane):
                    raise DamagedDataError(
                        f"dataset {dataset.name} does not hold plane {plane!r}",
                        hdu=dataset.name,
                        cell=key,
                    )
                planes[plane] = dataset[()]
        with reading_errors(self.path, f"cell {key} contents"):
            common = self.metadata.cell_common  # a cell read alone describes itself
            return CellCoadd(**planes, inputs=inputs, **identity, common=common)

    def _read_inputs(self, key: tuple[int, int], group: h5py.Group) -> list[InputRecord]:
        with reading_errors(self.path, f"cell {key} inputs"):
            dataset = _plain_dataset(group, cell_planes.INPUTS, self._size)
            if dataset.ndim != 1 or dataset.dtype.names is None:
                raise DamagedDataError(
                    f"inputs dataset has shape {dataset.shape}, dtype {dataset.dtype}",
                    hdu=dataset.name,
                    cell=key,
                )
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


def _optional_planes() -> frozenset[str]:
    """Names of the optional planes (stored only when the cells have them)."""
    return frozenset(spec.name for spec in cell_planes.PLANES if spec.optional)


def _plain_link(group: h5py.Group, name: str) -> Any:
    """``group[name]``, refused unless it is a hard link to an object of this file (soft
    and external links could make a cell or plane come from elsewhere)."""
    link = group.get(name, getlink=True)
    if link is None:
        raise DamagedDataError(f"{group.name}/{name} is missing", hdu=f"{group.name}/{name}")
    if not isinstance(link, h5py.HardLink):
        raise DamagedDataError(
            f"{group.name}/{name} is a {type(link).__name__}, not an object here",
            hdu=f"{group.name}/{name}",
        )
    return group[name]


def _single_name(obj: h5py.HLObject) -> None:
    """Refuse an object reachable under several names (extra hard links): another cell
    or plane would silently read the same bytes."""
    count = h5py.h5o.get_info(obj.id).rc
    if count != 1:
        raise DamagedDataError(f"{obj.name} is linked from {count} places", hdu=obj.name)


def _check_members(group: h5py.Group, expected: frozenset[str], *, exact: bool) -> None:
    names = set(group)
    missing = sorted(expected - names)
    if missing:
        raise DamagedDataError(f"{group.name} lacks {missing}", hdu=group.name)
    if exact and names != expected:
        raise DamagedDataError(
            f"{group.name} holds unexpected objects {sorted(names - expected)}", hdu=group.name
        )


def _plain_dataset(group: h5py.Group, name: str, file_size: int) -> h5py.Dataset:
    """``group[name]``: a contiguous or chunked dataset stored in this file, under one
    name, that really stores the bytes its shape declares (checked before reading it)."""
    dataset = _plain_link(group, name)
    if not isinstance(dataset, h5py.Dataset):
        raise DamagedDataError(f"{dataset.name} is not a dataset", hdu=dataset.name)
    _single_name(dataset)
    plist = dataset.id.get_create_plist()
    layout = plist.get_layout()
    if layout not in (h5py.h5d.CONTIGUOUS, h5py.h5d.CHUNKED):
        kind = {h5py.h5d.VIRTUAL: "virtual", h5py.h5d.COMPACT: "compact"}.get(layout, layout)
        raise DamagedDataError(f"{dataset.name} is a {kind} dataset", hdu=dataset.name)
    if plist.get_external_count() > 0:
        raise DamagedDataError(f"{dataset.name} keeps its data in external files", hdu=dataset.name)
    declared = dataset.size * dataset.dtype.itemsize
    if declared == 0:
        return dataset
    stored = dataset.id.get_storage_size()
    if stored > file_size:
        raise DamagedDataError(
            f"{dataset.name} stores {stored} bytes, more than the file's {file_size}",
            hdu=dataset.name,
        )
    checks_only = (h5py.h5z.FILTER_FLETCHER32, h5py.h5z.FILTER_SHUFFLE)
    filtered = layout == h5py.h5d.CHUNKED and any(
        plist.get_filter(i)[0] not in checks_only for i in range(plist.get_nfilters())
    )
    limit = _MAX_COMPRESSION * stored if filtered else stored
    if stored == 0 or declared > limit:
        raise DamagedDataError(
            f"{dataset.name} declares {dataset.shape} ({declared} bytes) but stores {stored}",
            hdu=dataset.name,
        )
    return dataset


def _per_input(plane: str) -> bool:
    return bool(cell_planes.plane(plane).per_input)


def _holds(dataset: h5py.Dataset, plane: str) -> bool:
    """Whether ``dataset`` says it holds ``plane`` (its ``plane`` attribute)."""
    return _attr_text(dataset.attrs.get("plane", b"")) == plane


def _attr_text(value: Any) -> str:
    if isinstance(value, (bytes, np.bytes_)):
        return bytes(value).decode("ascii")
    return str(value)
