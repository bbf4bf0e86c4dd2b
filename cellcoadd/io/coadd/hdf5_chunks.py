"""HDF5 chunks written as stored: data plus HDF5's Fletcher-32 checksum, computed with numpy.

Every non-empty dataset of an uncompressed cellcoadd HDF5 file is one chunk with HDF5's
Fletcher-32 filter. Writing it through ``H5Dwrite`` passes the chunk through HDF5's chunk
cache and its filter, which sums the bytes one 16-bit word at a time. Here the chunk is
assembled as HDF5 stores it (the data bytes followed by the checksum, four bytes
little-endian) and handed to ``H5Dwrite_chunk`` (h5py ``write_direct_chunk``) with all
filters marked as applied. Readers are unchanged: HDF5 verifies the checksum on every read,
so a wrong one could not go unnoticed (``tests/test_fast_writes.py`` also compares it with
HDF5's own for many sizes and contents). :class:`ObjectMaker` makes the groups, datasets
and attributes with h5py's low-level API, copying the datasets every cell repeats from
templates.

HDF5's Fletcher-32 (``H5_checksum_fletcher32``) runs over the bytes as big-endian 16-bit
words ``w_j`` (an odd last byte is the high byte of a last word) and keeps two sums,
folded modulo 65535 to 16 bits::

    sum1 = sum_j w_j                 sum2 = sum_j (n - j) w_j          (j = 0 .. n-1)
    checksum = (sum2 << 16) | sum1

Folding maps a positive sum to [1, 65535] (never 0), so each half is 0 only for all-zero
data and otherwise ``(s - 1) mod 65535 + 1``. Because ``2**16 == 1`` modulo 65535, a
big-endian word equals 256 times the little-endian word of the same two bytes, modulo
65535: the sums are taken over the native little-endian 16-bit view without swapping
bytes, as the row sums and column sums of blocks of words (two vectorised reductions).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import h5py
import numpy as np
from h5py import h5a, h5d, h5g, h5o, h5p, h5s, h5t

from cellcoadd.errors import CellCoaddValueError

#: Modulus of the Fletcher-32 sums.
_MOD = 65535
#: Longest block row, in 16-bit words (row sums fit in uint32), and the shortest preferred.
_MAX_ROW = 4096
_MIN_ROW = 512
#: Rows per slab: column sums of up to this many rows fit in uint32 (65537 * 65535 < 2**32).
_SLAB_ROWS = 65536
#: Bytes of the checksum HDF5 appends to a chunk.
_CHECKSUM_BYTES = 4
#: Row length by number of words (:func:`_row_length`).
_ROWS: dict[int, int] = {}


def fletcher32(data: np.ndarray | bytes | memoryview) -> int:
    """HDF5's Fletcher-32 checksum of the bytes of ``data`` (as ``H5_checksum_fletcher32``).

    Parameters
    ----------
    data : array or bytes-like
        The bytes as HDF5 stores them (a contiguous array is taken as its raw bytes).

    Returns
    -------
    int
        The 32-bit checksum; HDF5 stores it after the data, little-endian.
    """
    raw = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
    raw = np.ascontiguousarray(raw).reshape(-1).view(np.uint8)
    if raw.size % 2:  # an odd last byte is the high byte of a last word: a zero byte follows
        raw = np.concatenate((raw, np.zeros(1, dtype=np.uint8)))
    return int(fletcher32_rows(raw[np.newaxis])[0])


def fletcher32_rows(data: np.ndarray) -> np.ndarray:
    """:func:`fletcher32` of each row of the 2-D uint8 array ``data``, all at once.

    The rows may lie anywhere in memory (an even row stride; the bytes of a row
    contiguous), e.g. the data parts of chunk buffers that each end with a checksum.

    Returns
    -------
    numpy.ndarray
        uint32 checksums, one per row.
    """
    if data.ndim != 2 or data.dtype != np.uint8 or data.strides[1] != 1:
        raise CellCoaddValueError("expected a 2-D uint8 array with contiguous rows")
    if data.shape[1] % 2 or data.strides[0] % 2:
        return np.array([fletcher32(np.ascontiguousarray(row)) for row in data], np.uint32)
    words = data.view("<u2")
    n_rows, n_words = words.shape
    row = _row_length(n_words)
    body = n_words - n_words % row
    sum1 = np.zeros(n_rows, dtype=np.uint64)  # exact sums of the little-endian words
    sum2 = np.zeros(n_rows, dtype=np.uint64)  # sum_j (n - j) v_j, modulo 65535
    for start in range(0, body, row * _SLAB_ROWS):
        stop = min(body, start + row * _SLAB_ROWS)
        block = np.lib.stride_tricks.as_strided(
            words[:, start:],
            shape=(n_rows, (stop - start) // row, row),
            strides=(words.strides[0], 2 * row, 2),
            writeable=False,
        )
        # rows < 2**28, weights < 2**16, columns < 2**32, k < 2**12: no uint64 overflows
        rows = np.add.reduce(block, axis=2, dtype=np.uint32).astype(np.uint64)
        columns = np.add.reduce(block, axis=1, dtype=np.uint32).astype(np.uint64)
        sum1 += rows.sum(axis=1)
        # (n - j) for j = start + r * row + k is (n - start - r * row) - k
        weights = (n_words - start - row * np.arange(rows.shape[1], dtype=np.uint64)) % _MOD
        positions = (columns @ np.arange(row, dtype=np.uint64)) % _MOD
        sum2 = (sum2 + (rows @ weights) % _MOD + _MOD - positions) % _MOD
    if body < n_words:
        tail = words[:, body:].astype(np.uint64)
        sum1 += tail.sum(axis=1)
        sum2 = (sum2 + tail @ np.arange(n_words - body, 0, -1, dtype=np.uint64)) % _MOD
    # folding: a positive sum ends in [1, 65535]; both sums are 0 only for all-zero data
    low, high = (256 * sum1) % _MOD, (256 * sum2) % _MOD
    low[low == 0], high[high == 0] = _MOD, _MOD
    checksums = (high << np.uint64(16)) | low
    checksums[sum1 == 0] = 0
    return checksums.astype(np.uint32)


def _row_length(n_words: int) -> int:
    """Words per block row for ``n_words`` words: a divisor of it between :data:`_MIN_ROW`
    and :data:`_MAX_ROW` when there is one (no tail to sum apart), else the longest."""
    row = _ROWS.get(n_words)
    if row is None:
        longest = max(1, min(n_words, _MAX_ROW))
        candidates = range(longest, min(longest, _MIN_ROW) - 1, -1)
        row = next((length for length in candidates if n_words % length == 0), longest)
        if len(_ROWS) > 1024:
            _ROWS.clear()
        _ROWS[n_words] = row
    return row


class ChunkScratch:
    """A buffer reused for the stored chunks of successive datasets (data + checksum)."""

    def __init__(self) -> None:
        self._buffer = np.empty(0, dtype=np.uint8)

    def chunk(self, data: np.ndarray) -> memoryview:
        """The chunk HDF5 stores for the contiguous little-endian array ``data`` with the
        Fletcher-32 filter: its bytes, then their checksum (summed over the copy, while it
        is in the cache); valid until the next call."""
        return self.chunks([data])[0]

    def chunks(self, arrays: Sequence[np.ndarray]) -> list[memoryview]:
        """:meth:`chunk` of several arrays of one size (valid until the next call).

        The copies are rows of one buffer, each followed by its checksum, and the
        checksums of all rows are computed together (:func:`fletcher32_rows`): a few numpy
        calls for all, which matters when this runs in a thread beside HDF5 calls.
        Only numpy works here (it releases the GIL): safe in a worker thread.
        """
        size = arrays[0].nbytes if arrays else 0
        if any(array.nbytes != size for array in arrays):
            raise CellCoaddValueError("arrays of different sizes")
        width = size + _CHECKSUM_BYTES
        if self._buffer.size < width * len(arrays):
            self._buffer = np.empty(max(width * len(arrays), 2 * self._buffer.size), np.uint8)
        rows = self._buffer[: width * len(arrays)].reshape(len(arrays), width)
        for row, array in zip(rows, arrays, strict=True):
            row[:size] = np.ascontiguousarray(array).reshape(-1).view(np.uint8)
        checksums = fletcher32_rows(rows[:, :size]).astype("<u4")
        rows[:, size:] = checksums.view(np.uint8).reshape(len(arrays), _CHECKSUM_BYTES)
        return [row.data for row in rows]


#: An attribute: name and value (str values are stored as fixed-length byte strings).
Attribute = tuple[str, Any]
#: A dataset of :meth:`ObjectMaker.group_of`: name, data, attributes, stored chunk or None.
Member = tuple[str, np.ndarray, Sequence[Attribute], memoryview | None]


class ObjectMaker:
    """Groups, datasets and attributes made through h5py's low-level API.

    The same objects as h5py's ``create_group``, ``create_dataset(name, data=...,
    chunks=data.shape, fletcher32=True[, compression="gzip", compression_opts=1,
    shuffle=True])`` and ``attrs[name] = value`` make (no timestamps, ASCII names), without
    their per-call Python work: property lists and types are made once per write. An
    uncompressed chunk is written as stored (:meth:`ChunkScratch.chunk`); a compressed one
    goes through HDF5's filters. Empty arrays are contiguous datasets without checksum.

    A dataset made once per cell with the same name, shape, dtype and attributes
    (``repeated=True``) is copied (``H5Ocopy``) from a template with its attributes, made
    once in an in-memory HDF5 file: a copy costs less than creating the dataset and each
    attribute. Use as a context manager (the in-memory file is closed on leaving).

    Parameters
    ----------
    compress : bool
        Shuffle + gzip level 1 before the Fletcher-32 checksum.
    libver : (str, str)
        HDF5 object format bounds of the file written (those of the templates' file).
    """

    def __init__(self, compress: bool, libver: tuple[str, str] = ("v110", "v110")) -> None:
        self.compress = compress
        self.libver = libver
        self._lcpl = h5p.create(h5p.LINK_CREATE)
        self._lcpl.set_create_intermediate_group(True)
        self._lcpl.set_char_encoding(h5t.CSET_ASCII)
        self._gcpl = h5p.create(h5p.GROUP_CREATE)
        self._gcpl.set_obj_track_times(False)
        self._copy = h5p.create(h5p.OBJECT_COPY)
        self._dcpls: dict[tuple[tuple[int, ...], int], h5p.PropDCID] = {}
        self._types: dict[tuple[np.dtype, bool], h5t.TypeID] = {}
        self._spaces: dict[tuple[int, ...], h5s.SpaceID] = {}
        self._templates: h5py.File | None = None
        self._scratch = ChunkScratch()
        self._template_names: dict[Any, bytes] = {}

    def __enter__(self) -> ObjectMaker:
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self._templates is not None:
            self._templates.close()
            self._templates = None
        self._template_names = {}

    def group(self, parent: h5g.GroupID, name: str) -> h5g.GroupID:
        """A new group ``name`` in ``parent``."""
        return h5g.create(parent, _name(name), lcpl=self._lcpl, gcpl=self._gcpl)

    def group_of(self, parent: h5g.GroupID, name: str, members: Sequence[Member]) -> h5g.GroupID:
        """A new group ``name`` in ``parent`` holding the datasets ``members`` (name, data,
        attributes, chunk as for :meth:`dataset`), copied with one ``H5Ocopy`` from a
        template group made once for their names, shapes, dtypes and attributes; the
        chunks are then written. Falls back to :meth:`group` and :meth:`dataset` for
        attribute values that cannot be compared."""
        key = tuple(
            (member, data.shape, data.dtype, tuple(attrs)) for member, data, attrs, _ in members
        )
        try:
            template = self._template_names.get(key)
        except TypeError:  # an unhashable value
            group = self.group(parent, name)
            for member, data, attrs, chunk in members:
                self.dataset(group, member, data, attrs, chunk=chunk)
            return group
        if template is None:
            template = f"g{len(self._template_names)}".encode("ascii")
            made = self.group(self._templates_group(), template.decode("ascii"))
            for member, data, attrs, _ in members:
                dataset = self._create(made, _name(member), data, len(attrs))
                try:
                    self.attributes(dataset, attrs)
                finally:
                    dataset.close()
            self._template_names[key] = template
        h5o.copy(self._templates_group(), template, parent, _name(name), self._copy, self._lcpl)
        group = h5g.open(parent, _name(name))
        for member, data, _, chunk in members:
            if data.size:
                dataset = h5d.open(group, _name(member))
                try:
                    self._write(dataset, np.ascontiguousarray(data), chunk)
                finally:
                    dataset.close()
        return group

    def dataset(
        self,
        parent: h5g.GroupID,
        name: str,
        data: np.ndarray,
        attributes: Sequence[Attribute] = (),
        *,
        repeated: bool = False,
        chunk: memoryview | None = None,
    ) -> None:
        """Dataset ``name`` in ``parent`` holding ``data``, with its ``attributes``.

        ``repeated``: copied from a template (see the class description). ``chunk``: the
        stored chunk of ``data`` (:meth:`ChunkScratch.chunks`) when already made; made
        here otherwise (ignored for compressed and empty datasets).
        """
        data = np.ascontiguousarray(data)
        template = self._template(name, data, attributes) if repeated and data.size else None
        if template is not None:
            h5o.copy(self._templates_group(), template, parent, _name(name), self._copy, self._lcpl)
            dataset = h5d.open(parent, _name(name))
            attributes = ()
        else:
            dataset = self._create(parent, _name(name), data, len(attributes))
        try:
            if data.size:
                self._write(dataset, data, chunk)
            self.attributes(dataset, attributes)
        finally:
            dataset.close()

    def _write(self, dataset: h5d.DatasetID, data: np.ndarray, chunk: memoryview | None) -> None:
        """Write the non-empty ``data`` of a new ``dataset``: its stored chunk directly, or
        through HDF5's filters when compressed."""
        if self.compress:
            dataset.write(h5s.ALL, h5s.ALL, data, mtype=self._type(data.dtype, logical=False))
            return
        write_chunk(
            dataset, (0,) * data.ndim, self._scratch.chunk(data) if chunk is None else chunk
        )

    def attributes(
        self, owner: h5g.GroupID | h5d.DatasetID, attributes: Sequence[Attribute]
    ) -> None:
        """Attach ``attributes`` (scalars) to the object ``owner``."""
        for name, value in attributes:
            array = np.asarray(np.bytes_(value) if isinstance(value, str) else value, order="C")
            space = self._space(array.shape)
            attribute = h5a.create(owner, _name(name), self._type(array.dtype, logical=True), space)
            try:
                attribute.write(array, mtype=self._type(array.dtype, logical=False))
            finally:
                attribute.close()

    def _create(
        self, parent: h5g.GroupID, name: bytes, data: np.ndarray, n_attributes: int
    ) -> h5d.DatasetID:
        file_type = self._type(data.dtype, logical=True)
        dcpl = self._dcpl(data.shape, n_attributes)
        space = self._space(data.shape)
        return h5d.create(parent, name, file_type, space, dcpl=dcpl, lcpl=self._lcpl)

    def _templates_group(self) -> h5g.GroupID:
        if self._templates is None:
            # a name of its own: HDF5 refuses to create a file of the name of an open one
            unique = f"cellcoadd-templates-{id(self):x}-{next(_TEMPLATE_FILES)}"
            self._templates = h5py.File(
                unique, "w", driver="core", backing_store=False, libver=self.libver
            )
        return self._templates.id

    def _template(
        self, name: str, data: np.ndarray, attributes: Sequence[Attribute]
    ) -> bytes | None:
        """Name (in the in-memory file) of the template of a repeated dataset; None for
        attribute values that cannot be compared (the dataset is then made directly)."""
        key = (name, data.shape, data.dtype, tuple(attributes))
        try:
            made = self._template_names.get(key)
        except TypeError:  # an unhashable value
            return None
        if made is None:
            made = f"{len(self._template_names)}".encode("ascii")
            dataset = self._create(self._templates_group(), made, data, len(attributes))
            try:
                self.attributes(dataset, attributes)
            finally:
                dataset.close()
            self._template_names[key] = made
        return made

    def _space(self, shape: tuple[int, ...]) -> h5s.SpaceID:
        space = self._spaces.get(shape)
        if space is None:
            space = self._spaces[shape] = h5s.create_simple(shape)
        return space

    def _type(self, dtype: np.dtype, *, logical: bool) -> h5t.TypeID:
        key = (dtype, logical)
        made = self._types.get(key)
        if made is None:
            made = self._types[key] = h5t.py_create(dtype, logical=logical)
        return made

    def _dcpl(self, shape: tuple[int, ...], n_attributes: int) -> h5p.PropDCID:
        """Creation properties: one chunk of ``shape`` with Fletcher-32 (contiguous if
        empty), room for the attributes in the object header (HDF5 moves more than 8 to a
        separate heap by default, which costs more than they hold)."""
        compact = max(8, n_attributes)
        key = (shape if math.prod(shape) else (), compact)
        dcpl = self._dcpls.get(key)
        if dcpl is None:
            dcpl = h5p.create(h5p.DATASET_CREATE)
            dcpl.set_obj_track_times(False)
            dcpl.set_attr_phase_change(compact, 6)
            if key[0]:
                dcpl.set_chunk(shape)
                if self.compress:
                    dcpl.set_shuffle()
                    dcpl.set_deflate(1)
                dcpl.set_fletcher32()
            self._dcpls[key] = dcpl
        return dcpl


#: Numbers of the in-memory template files.
_TEMPLATE_FILES = itertools.count()


def write_chunk(dataset: h5d.DatasetID, offset: tuple[int, ...], chunk: memoryview) -> None:
    """Store ``chunk`` (data and checksum) as the chunk at ``offset``, filters applied."""
    dataset.write_direct_chunk(offset, chunk, filter_mask=0)


def _name(name: str) -> bytes:
    return name.encode("ascii")
