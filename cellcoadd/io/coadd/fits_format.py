"""FITS layout of a patch coadd (fitsio). See ``docs/format.md`` for the full description.

HDU 0 (primary, no data) carries the identification and version keywords and
``FILESIZE`` (the file's length in bytes, filled in last; readers check it instead of
walking every header to the end of the file, and fall back to that walk without it), HDU 1
``METADATA`` the metadata JSON as a uint8 image, HDU 2 ``CELLINDEX`` one row per cell
(index, HDU numbers of its planes, identity JSON), then one HDU per (cell, plane) named
``CELL_<+cx>_<+cy>_<PLANE>``, planes in the order of :data:`~cellcoadd.model.planes.PLANES`
followed by the inputs table (an optional plane a cell lacks, such as ``psf_corners`` of a
build without it, has no HDU and ``-1`` in its ``CELLINDEX`` column, which files before
format 1.4 do not have). Every HDU carries CHECKSUM/DATASUM and ``DATACRC``, the CRC-32
of its data unit as stored (see :mod:`cellcoadd.io._fits.checksums`), all verified on read
when ``verify`` is true.

With lossless compression (each plane's :attr:`~cellcoadd.model.planes.PlaneSpec.compression`)
the float32 planes are tile-compressed as floats with GZIP_2 and no quantization
(``ZQUANTIZ = 'NONE'``), so FITS viewers and readers decode them to the very floats, in
``BUNIT``. CFITSIO writes every non-finite value of such a plane as one NaN bit pattern
(0xFFFFFFFF); the pixels whose bits were different (infinities, NaN payloads, the usual
quiet NaN) are listed in the header, ``CCNFNUM`` of them in ``CCNFBITS`` (base64 of the
zlib-compressed little-endian uint32 position steps, in C order, then their uint32 bit
patterns), and put back on reading: the round trip is bit for bit. Files written before
stored those planes as int32 bit patterns with ``CCBITS = 'FLOAT32'``, still read. The mask
is RICE_1 compressed; the float64 PSF stamps, the tables and the metadata are never
compressed.

Every HDU of a plane on the cell's pixel grid (image, mask, variance, noise, mfrac) carries
the cell's WCS cards, so viewers place each of them on the sky (the noise cube's third
axis is the realization).
"""

from __future__ import annotations

import base64
import binascii
import itertools
import zlib
from collections.abc import Iterator, Sequence
from typing import Any, BinaryIO

import fitsio
import numpy as np
from fitsio.hdu import AsciiTableHDU, ImageHDU, TableHDU

from cellcoadd.errors import (
    CellCoaddFormatError,
    CellCoaddOSError,
    DamagedDataError,
    InvalidCoaddError,
)
from cellcoadd.geometry.tract import rubin_cell_index, rubin_patch_id
from cellcoadd.io._files.read_checks import check_path_readable, reading_errors
from cellcoadd.io._fits import direct as fits_direct
from cellcoadd.io._fits.checksums import (
    DATACRC_PLACEHOLDER,
    fill_datacrc,
    find_card,
    stabilise_fits_checksums,
    stable_checksum_header,
    verify_hdu,
)
from cellcoadd.io._fits.direct import UnsupportedCard, card
from cellcoadd.io._fits.paths import cfitsio_path, check_fits_path
from cellcoadd.io.coadd import format_version
from cellcoadd.io.coadd.cell_records import (
    CellIdentity,
    WcsRecords,
    cell_record_json,
    check_cell_geometry,
    expected_shapes,
    parse_cell_record,
)
from cellcoadd.io.coadd.coadd_file import CoaddFile
from cellcoadd.io.coadd.empty_cells import EMPTY_KEY, empty_plane, planes_without_pixels
from cellcoadd.io.coadd.format_version import (
    FILE_KIND,
    MAX_METADATA_BYTES,
    check_format_version,
    decode_metadata,
    sha256_hex,
)
from cellcoadd.io.coadd.inputs_table import inputs_from_array, inputs_to_array
from cellcoadd.model import planes as cell_planes
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.inputs import InputRecord
from cellcoadd.model.patch_coadd import PatchCoadd, PatchMetadata, check_planes
from cellcoadd.model.wcs_codec import wcs_to_record

_FIRST_CELL_HDU = 3
_FITS_MAGIC = b"SIMPLE  ="


def extname(index: tuple[int, int], plane: str) -> str:
    """EXTNAME of a cell plane, e.g. ``CELL_+03_-01_IMAGE``."""
    return f"CELL_{index[0]:+03d}_{index[1]:+03d}_{plane.upper()}"


def hdu_column(plane: str) -> str:
    """Column of ``CELLINDEX`` holding the HDU number of a cell's ``plane`` (or inputs)."""
    return f"HDU_{plane.upper()}"


def _cell_planes(n_noise: int, present: tuple[str, ...]) -> list[str]:
    """The HDUs of a cell holding the planes ``present``, in file order: its planes, then
    its inputs table."""
    # no zero-size images in FITS: with K = 0 the per-realization planes have no HDU;
    # an optional plane a cell lacks has none either (its CELLINDEX column says -1)
    return [
        *(
            spec.name
            for spec in cell_planes.PLANES
            if (n_noise > 0 or not spec.per_realization) and spec.name in present
        ),
        cell_planes.INPUTS,
    ]


def write_fits(patch: PatchCoadd, path: str, *, compress: bool) -> None:
    """Write ``patch`` to a new FITS file at ``path`` (replaced if it exists), complete with
    its CHECKSUM, DATASUM and ``DATACRC`` cards.

    Uncompressed cells are written directly (:mod:`cellcoadd.io._fits.direct`: the same
    bytes CFITSIO would write, in one pass); tile-compressed ones, and anything the direct
    writer does not reproduce exactly, through CFITSIO, followed by
    :func:`~cellcoadd.io._fits.checksums.stabilise_fits_checksums`.
    """
    cells = list(patch.cells.values())
    # every cell of a patch holds the same planes (PatchCoadd checks it)
    present = cells[0].plane_names if cells else cell_planes.required_plane_names()
    write_fits_cells(patch.metadata, cells, iter(cells), path, compress=compress, present=present)


def write_fits_cells(
    metadata: PatchMetadata,
    identities: Sequence[CellIdentity],
    cells: Iterator[CellCoadd],
    path: str,
    *,
    compress: bool,
    present: tuple[str, ...],
) -> None:
    """Write the patch of ``metadata`` from its ``cells`` as they come (as :func:`write_fits`).

    ``identities`` (tract, index, boxes, WCS of every cell, in sorted index order: the
    cells themselves, or their geometry) make the cell index at the head of the file;
    ``cells`` must then give those cells in that order, each written and let go before the
    next is taken (at most :data:`_BATCH` are held here). A cell whose identity is not the
    one announced, or holding planes other than ``present`` (names, as
    :attr:`CellCoadd.plane_names`), raises InvalidCoaddError.
    """
    check_fits_path(path)
    replay = _Replay(cells)
    if not compress:
        try:
            _write_fits(
                metadata, identities, replay, path, compress=False, direct=True, present=present
            )
            return
        except UnsupportedCard:
            # something only CFITSIO writes as CFITSIO does: the same file through it, from
            # the cells still held (a file's first cells show it, when none was let go)
            if not replay.replayable:
                raise
    _write_fits(
        metadata, identities, replay.again(), path, compress=compress, direct=False,
        present=present,
    )  # fmt: skip
    stabilise_fits_checksums(path)


#: The data of an HDU without pixels (an empty cell's plane, see empty_cells).
_NO_PIXELS = np.zeros((0,), dtype=np.int16)

#: Cells written together by the direct writer (its threads share them out).
_BATCH = 8


class _Replay:
    """The cells of an iterator, taken again from the start by :meth:`again` as long as no
    more than the first :data:`_BATCH` were taken (the others are not kept)."""

    def __init__(self, cells: Iterator[CellCoadd]) -> None:
        self._cells = cells
        self._taken: list[CellCoadd] | None = []

    @property
    def replayable(self) -> bool:
        return self._taken is not None

    def __iter__(self) -> Iterator[CellCoadd]:
        return self

    def __next__(self) -> CellCoadd:
        cell = next(self._cells)
        if self._taken is not None:
            self._taken.append(cell)
            if len(self._taken) > _BATCH:
                self._taken = None
        return cell

    def again(self) -> Iterator[CellCoadd]:
        assert self._taken is not None  # see replayable
        return itertools.chain(self._taken, self._cells)


def _write_fits(
    metadata: PatchMetadata,
    identities: Sequence[CellIdentity],
    cells: Iterator[CellCoadd],
    path: str,
    *,
    compress: bool,
    direct: bool,
    present: tuple[str, ...],
) -> None:
    # looked up on the module at each write, so tests can stand in for it
    payload, version = format_version.metadata_payload(metadata)
    indices = [identity.index for identity in identities]
    planes = _cell_planes(metadata.n_noise, present)
    n_hdu = _FIRST_CELL_HDU + len(planes) * len(indices)
    meta = metadata
    # BUNIT (+ MAGZERO) of image/noise/variance, MP_<NAME> = bit of the mask (format 1.2)
    unit_cards = meta.unit_cards()
    no_data = meta.mask_bits.value("NO_DATA")
    rubin_id = rubin_patch_id(meta.patch, meta.skymap_config)
    wcs_records = WcsRecords()
    index_table, records = _index_table(identities, planes, wcs_records, meta)
    arriving = _checked(cells, identities, records, wcs_records, present)
    # ignore_empty: header-only HDUs (an empty cell's planes) after the primary one
    with fitsio.FITS(cfitsio_path(path), "rw", clobber=True, ignore_empty=True) as fits:
        fits.write(
            None,
            header=[
                {"name": "CCFORMAT", "value": FILE_KIND, "comment": "cellcoadd file kind"},
                {"name": "CCVERS", "value": version, "comment": "format version MAJOR.MINOR"},
                {"name": "TRACT", "value": meta.tract, "comment": "tract number"},
                {"name": "PATCH_X", "value": meta.patch[0], "comment": "patch index x"},
                {"name": "PATCH_Y", "value": meta.patch[1], "comment": "patch index y"},
                {"name": "PATCHID", "value": rubin_id, "comment": "Rubin's patch id y * nx + x"},
                {"name": "NCELLS", "value": len(indices), "comment": "cells in this file"},
                {"name": "NHDU", "value": n_hdu, "comment": "HDUs in this file"},
                {"name": "SOFTVERS", "value": meta.software_version, "comment": "built by"},
                # the real value is written last, in place (same card, no header growth)
                {"name": "FILESIZE", "value": 0, "comment": "bytes in this file"},
                DATACRC_PLACEHOLDER,
            ],
        )
        fits[-1].write_checksum()
        _write_image(
            fits,
            np.frombuffer(payload, dtype=np.uint8),
            "METADATA",
            [{"name": "METASHA", "value": sha256_hex(payload), "comment": "SHA-256"}],
        )
        fits.write(index_table, extname="CELLINDEX", header=[DATACRC_PLACEHOLDER])
        fits[-1].write_checksum()
        if not direct:
            hdus: _CfitsioHdus | fits_direct.DirectHdus = _CfitsioHdus(fits, compress)
            for cell in arriving:
                _write_cell(
                    hdus, cell, plane_cards=unit_cards, records=wcs_records, no_data=no_data
                )
            # Readers check the length against it instead of walking every header to the end.
            size = fits[-1].get_offsets()["data_end"]
            fits[0].write_key("FILESIZE", size, comment="bytes in this file")
            fits[0].write_checksum()
            return
        head = [fits[number].get_offsets() for number in range(_FIRST_CELL_HDU)]
    with open(path, "r+b", buffering=0) as stream:  # (p)writev: a cell in one system call
        size = head[-1]["data_end"]
        for batch in iter(lambda: list(itertools.islice(arriving, _BATCH)), []):
            writer = fits_direct.DirectHdus()
            for cell in batch:
                _write_cell(
                    writer, cell, plane_cards=unit_cards, records=wcs_records, no_data=no_data
                )
            size = writer.write(stream, size)
            del batch, writer  # written: let go before the next batch comes
        stream.truncate(size)
        _finish_head(stream, head, size)


def _checked(
    cells: Iterator[CellCoadd],
    identities: Sequence[CellIdentity],
    records: list[str],
    wcs_records: WcsRecords,
    present: tuple[str, ...],
) -> Iterator[CellCoadd]:
    """``cells``, each checked to be the one announced in the cell index, holding the
    planes ``present`` (InvalidCoaddError otherwise, or when there are more or fewer)."""
    count = 0
    for cell in cells:
        if count >= len(identities):
            raise InvalidCoaddError(f"cell {cell.index}: more cells than the {count} announced")
        identity = identities[count]
        if cell is not identity and cell_record_json(cell, wcs_records) != records[count]:
            raise InvalidCoaddError(
                f"cell {cell.index} came where cell {identity.index} was announced, or its "
                "boxes or WCS differ from those announced"
            )
        check_planes(cell, present)
        count += 1
        yield cell
        del cell  # written: not held here while the next one is made
    if count != len(identities):
        raise InvalidCoaddError(
            f"{count} cells came of the {len(identities)} announced; cell "
            f"{identities[count].index} is missing"
        )


def _finish_head(stream: BinaryIO, head: list[dict[str, int]], size: int) -> None:
    """Fill in ``FILESIZE`` and the ``DATACRC`` of the HDUs CFITSIO wrote, stabilise their
    checksum cards (as :func:`~cellcoadd.io._fits.checksums.stabilise_fits_checksums`)."""
    for number, extent in enumerate(head):
        start, data_start, end = extent["header_start"], extent["data_start"], extent["data_end"]
        header = bytearray(_read_at(stream, start, data_start - start))
        crc = zlib.crc32(_read_at(stream, data_start, end - data_start))
        if number == 0:
            at = find_card(header, b"FILESIZE=")
            if at < 0:
                raise UnsupportedCard("FILESIZE card missing")
            header[at : at + 80] = card("FILESIZE", size, "bytes in this file")
        fill_datacrc(header, crc)
        stable_checksum_header(header)
        stream.seek(start)
        fits_direct.write_parts(stream, [bytes(header)])


def _read_at(stream: BinaryIO, offset: int, size: int) -> bytes:
    """``size`` bytes of ``stream`` from ``offset`` (an unbuffered read may return fewer)."""
    stream.seek(offset)
    chunks = []
    while size > 0:
        chunk = stream.read(size)
        if not chunk:
            raise CellCoaddOSError(
                f"{getattr(stream, 'name', 'file')}: ends before byte {offset + size}"
            )
        chunks.append(chunk)
        size -= len(chunk)
    return b"".join(chunks)


def _index_table(
    identities: Sequence[CellIdentity],
    planes: list[str],
    wcs_records: WcsRecords | None,
    metadata: PatchMetadata,
) -> tuple[np.ndarray, list[str]]:
    """The CELLINDEX table of the cells of ``identities`` and their identity records
    (with Rubin's patch-local index of each cell, informative: format 1.6)."""
    records = [cell_record_json(identity, wcs_records) for identity in identities]
    width = max([1, *(len(text) for text in records)])
    dtype = [("CELL_X", "<i8"), ("CELL_Y", "<i8")]
    dtype += [(hdu_column(plane), "<i4") for plane in cell_planes.cell_objects()]
    dtype += [("RUBIN_X", "<i4"), ("RUBIN_Y", "<i4"), ("CELL", f"S{width}")]
    table = np.zeros(len(records), dtype=dtype)
    for row, (identity, text) in enumerate(zip(identities, records, strict=True)):
        first = _FIRST_CELL_HDU + row * len(planes)
        table[row]["CELL_X"], table[row]["CELL_Y"] = identity.index
        table[row]["RUBIN_X"], table[row]["RUBIN_Y"] = rubin_cell_index(
            identity.index, metadata.patch, metadata.skymap_config
        )
        for plane in cell_planes.cell_objects():
            number = first + planes.index(plane) if plane in planes else -1
            table[row][hdu_column(plane)] = number
        table[row]["CELL"] = text.encode("ascii")
    return table, records


class _CfitsioHdus:
    """Cell HDUs written through CFITSIO (tile compression; the fallback)."""

    def __init__(self, fits: fitsio.FITS, compress: bool) -> None:
        self.fits = fits
        self.compress = compress

    def image(self, plane: str, data: np.ndarray, name: str, keys: list[dict[str, Any]]) -> None:
        compression = cell_planes.plane(plane).compression if self.compress else "none"
        if not data.size:  # no pixels: a header-only HDU (NAXIS = 0, BITPIX = 16)
            self.fits.create_image_hdu(dims=None, dtype=np.int16, extname=name)
            self.fits[-1].write_keys([*keys, DATACRC_PLACEHOLDER])
            self.fits[-1].write_checksum()
        elif compression == "float_bits":
            keys = [*keys, *_nonfinite_keys(data)]
            _write_image(self.fits, data, name, keys, compress="GZIP_2")
        elif compression == "integer":
            _write_image(self.fits, data, name, keys, compress="RICE_1")
        else:
            _write_image(self.fits, data, name, keys)

    def table(self, table: np.ndarray, name: str, keys: list[dict[str, Any]]) -> None:
        self.fits.write(table, extname=name)
        self.fits[-1].write_keys([*keys, DATACRC_PLACEHOLDER])
        self.fits[-1].write_checksum()


#: The one bit pattern CFITSIO writes for every non-finite value of a compressed float plane.
_CFITSIO_NAN = np.uint32(0xFFFFFFFF)


def _nonfinite_keys(data: np.ndarray) -> list[dict[str, Any]]:
    """``CCNFNUM``/``CCNFBITS`` listing the pixels CFITSIO's float compression would change
    (non-finite values other than its own NaN); none when there are none."""
    values = np.ascontiguousarray(data, dtype=np.float32).reshape(-1)
    bits = values.view(np.uint32)
    where = np.flatnonzero(~np.isfinite(values) & (bits != _CFITSIO_NAN))
    if where.size == 0:
        return []
    steps = np.diff(where, prepend=0).astype("<u4")  # mostly 1 in NaN regions: compresses
    payload = zlib.compress(steps.tobytes() + bits[where].astype("<u4").tobytes(), 9)
    return [
        {"name": "CCNFNUM", "value": int(where.size), "comment": "non-finite pixels restored"},
        {"name": "CCNFBITS", "value": base64.b64encode(payload).decode("ascii")},
    ]


def _restore_nonfinite(data: np.ndarray, header: Any, path: str, context: str) -> np.ndarray:
    """Put back the bit patterns listed by :func:`_nonfinite_keys`.

    Raises ``CellCoaddFormatError`` naming ``path`` and ``context`` (the cell and plane)
    when the list is corrupt or does not fit the plane.
    """

    def fail(problem: str) -> CellCoaddFormatError:
        return CellCoaddFormatError(path, f"{context}: {problem}")

    count = header.get("CCNFNUM")
    if count is None:
        return data
    if isinstance(count, bool) or not isinstance(count, int) or not 0 < count <= data.size:
        raise fail(f"CCNFNUM = {count!r}")
    try:
        raw = zlib.decompress(base64.b64decode(str(header.get("CCNFBITS", "")), validate=True))
    except (binascii.Error, zlib.error) as err:
        raise fail(f"CCNFBITS cannot be decoded: {err}") from None
    if len(raw) != 8 * count:
        raise fail(f"CCNFBITS holds {len(raw)} bytes, expected {8 * count}")
    where = np.cumsum(np.frombuffer(raw[: 4 * count], dtype="<u4").astype(np.int64))
    restored = np.frombuffer(raw[4 * count :], dtype="<u4")
    out = np.array(data, dtype=np.float32, copy=True).reshape(-1)
    bits = out.view(np.uint32)
    if where[-1] >= out.size or np.any(np.diff(where) <= 0) or np.any(bits[where] != _CFITSIO_NAN):
        raise fail("CCNFBITS lists pixels that are not the compressed NaNs")
    if np.any(np.isfinite(restored.view(np.float32))):
        raise fail("CCNFBITS restores finite values")
    bits[where] = restored
    return out.reshape(data.shape)


def _write_cell(
    hdus: _CfitsioHdus | fits_direct.DirectHdus,
    cell: CellCoadd,
    *,
    plane_cards: dict[str, list[tuple[str, object, str]]] | None = None,
    records: WcsRecords | None = None,
    no_data: int = 0,
) -> None:
    """The HDUs of ``cell``: its planes (an empty cell's without pixels, see
    :mod:`~cellcoadd.io.coadd.empty_cells`; ``no_data``: the ``NO_DATA`` bit's value),
    then its inputs table."""
    keys: list[dict[str, Any]] = [
        {"name": "CELL_X", "value": cell.index[0], "comment": "tract-global cell index x"},
        {"name": "CELL_Y", "value": cell.index[1], "comment": "tract-global cell index y"},
    ]
    bare = planes_without_pixels(cell, no_data)
    for plane in _cell_planes(cell.n_noise, cell.plane_names):
        name = extname(cell.index, plane)
        plane_keys: list[dict[str, Any]] = [*keys, {"name": "PLANE", "value": plane}]
        if plane == cell_planes.INPUTS:
            hdus.table(inputs_to_array(cell.inputs, ascii_only=True), name, plane_keys)
            continue
        if plane in bare:  # an empty cell's plane: a header saying so, no pixels (1.6)
            empty = {"name": EMPTY_KEY, "value": True, "comment": "no data: NaN or NO_DATA"}
            hdus.image(plane, _NO_PIXELS, name, [*plane_keys, empty])
            continue
        plane_keys += [
            {"name": key, "value": value, "comment": comment}
            for key, value, comment in (plane_cards or {}).get(plane, [])
        ]
        if cell_planes.plane(plane).on_cell_grid:
            # Standard WCS cards so viewers can place every pixel plane; the exact WCS is in
            # CELLINDEX.
            plane_keys += _wcs_cards(cell, records)
        hdus.image(plane, getattr(cell, plane), name, plane_keys)


def _wcs_cards(cell: CellCoadd, records: WcsRecords | None = None) -> list[dict[str, Any]]:
    return [
        {"name": key, "value": value}
        for key, value in (records or wcs_to_record)(cell.wcs)["header"]
        if key not in ("COMMENT", "HISTORY", "")
    ]


def _write_image(
    fits: fitsio.FITS,
    data: np.ndarray,
    name: str,
    keys: list[dict[str, Any]],
    compress: str | None = None,
) -> None:
    options: dict[str, Any] = {}
    if compress is not None:
        options = {"compress": compress, "tile_dims": data.shape, "qlevel": None}
    # Create then write: fitsio's one-step write maps all non-finite floats to one NaN.
    fits.create_image_hdu(dims=data.shape, dtype=data.dtype, extname=name, **options)
    hdu = fits[-1]
    hdu.write(np.ascontiguousarray(data))
    hdu.write_keys([*keys, DATACRC_PLACEHOLDER])
    hdu.write_checksum()


class FitsCoaddFile(CoaddFile):
    """Lazy reader of the FITS layout (see the module docstring)."""

    format_name = "fits"

    def __init__(self, path: str, *, verify: bool = True) -> None:
        check_fits_path(path)
        size = check_path_readable(path)
        # Kept open for the checksums: verify_hdu reads an HDU's bytes as stored.
        self._raw: Any = open(path, "rb")  # closed by close()
        self._fits: Any = None
        try:
            if self._raw.read(len(_FITS_MAGIC)) != _FITS_MAGIC:
                raise CellCoaddFormatError(path, "not a FITS file (it does not start with SIMPLE)")
            self.path = path
            self.verify = verify
            self._opened: dict[int, Any] = {}  # fitsio HDU objects by number
            self._n_hdu = 0
            with reading_errors(path, "cannot open the FITS file"):
                self._fits = fitsio.FITS(cfitsio_path(path))
            metadata, rows = self._read_header_part(path, size)
        except BaseException:
            self.close()
            raise
        self._rows = rows
        super().__init__(path, metadata, list(rows))

    def _read_header_part(
        self, path: str, size: int
    ) -> tuple[PatchMetadata, dict[tuple[int, int], np.void]]:
        with reading_errors(path, "reading the primary header"):
            primary = self._hdu_at(0).read_header()
            kind = primary.get("CCFORMAT")
            if kind != FILE_KIND:
                raise CellCoaddFormatError(
                    path, f"not a cellcoadd patch file (CCFORMAT = {kind!r})"
                )
            version = str(primary.get("CCVERS"))
            check_format_version(path, version)
            n_hdu = int(primary["NHDU"])
            declared_size = primary.get("FILESIZE")
        self._n_hdu = n_hdu
        if declared_size is not None:
            # Written last by the writer: a cheap check that nothing was cut or appended.
            if declared_size != size:
                raise CellCoaddFormatError(
                    path, f"the file has {size} bytes, its header says {declared_size}: truncated?"
                )
        else:
            self._check_last_hdu(n_hdu, size)
        self._verify_hdu(0, "PRIMARY")
        hdu = self._hdu(1, "METADATA")
        with reading_errors(path, "reading the metadata"):
            dims = hdu.get_dims()
            if len(dims) != 1 or not 0 < dims[0] <= MAX_METADATA_BYTES:
                raise DamagedDataError(f"METADATA has dimensions {dims}", hdu="METADATA")
            payload = hdu.read().astype(np.uint8, copy=False).tobytes()
            digest = hdu.read_header().get("METASHA")
            if digest != sha256_hex(payload):
                raise CellCoaddFormatError(path, "metadata SHA-256 mismatch: corrupted metadata")
            metadata = decode_metadata(path, payload, version)
        hdu = self._hdu(2, "CELLINDEX")
        with reading_errors(path, "reading the cell index"):
            table = hdu.read()
            rows = {(int(r["CELL_X"]), int(r["CELL_Y"])): r for r in table}
            if len(rows) != len(table):
                raise DamagedDataError("the cell index lists a cell twice")
        return metadata, rows

    def _check_last_hdu(self, n_hdu: int, size: int) -> None:
        """The last HDU must end where the file does: then no HDU is missing or added.

        For files without FILESIZE: reaching the last HDU walks every header of the file.
        """
        try:
            last = self._hdu_at(n_hdu - 1)
        except CellCoaddFormatError:
            raise CellCoaddFormatError(
                self.path, f"the file has fewer HDUs than the {n_hdu} its header says: truncated?"
            ) from None
        with reading_errors(self.path, "checking the file length"):
            end = last.get_offsets()["data_end"]
        if end != size:
            raise CellCoaddFormatError(
                self.path, f"the last HDU ends at byte {end} but the file has {size} bytes"
            )

    def _hdu_at(self, number: int) -> Any:
        """HDU ``number`` (0-based), reached without listing the file's HDUs first.

        ``fitsio.FITS[...]`` first builds the list of every HDU, reading all headers of the
        file (about 3400 for a 22 x 22-cell patch, ~0.3 s) even to reach one cell. Moving
        to one HDU only walks CFITSIO's chain of header sizes (~10 us per HDU), so the
        fitsio HDU object is made directly on the open file.
        """
        hdu = self._opened.get(number)
        if hdu is None:
            with reading_errors(self.path, f"reading HDU {number}"):
                kind = self._fits.movabs_ext(number)
                hdu_class = {
                    fitsio.IMAGE_HDU: ImageHDU,
                    fitsio.BINARY_TBL: TableHDU,
                    fitsio.ASCII_TBL: AsciiTableHDU,
                }[kind]
                try:
                    hdu = hdu_class(self._fits._FITS, number)  # fitsio's handle of the file
                except (AttributeError, TypeError):  # other fitsio internals: its slow path
                    hdu = self._fits[number]
            self._opened[number] = hdu
        return hdu

    def _hdu(self, number: int, name: str) -> Any:
        """HDU ``number``, checked to be named ``name`` and (if verifying) its checksum."""
        if not 0 <= number < self._n_hdu:
            raise CellCoaddFormatError(self.path, f"HDU {name} (number {number}) is missing")
        hdu = self._hdu_at(number)
        with reading_errors(self.path, f"reading HDU {number} ({name})"):
            found = hdu.get_extname()
        if found != name:
            raise CellCoaddFormatError(self.path, f"HDU {number} is {found!r}, expected {name!r}")
        self._verify_hdu(number, name)
        return hdu

    def _verify_hdu(self, number: int, name: str) -> None:
        if not self.verify:
            return
        with reading_errors(self.path, f"checksum of HDU {number} {name}".rstrip()):
            verify_hdu(self._raw, self._hdu_at(number).get_offsets())

    def _row(self, index: tuple[int, int]) -> tuple[tuple[int, int], np.void]:
        key = self._check_index(index)
        return key, self._rows[key]

    def read_cell(self, index: tuple[int, int]) -> CellCoadd:
        key, row = self._row(index)
        with reading_errors(self.path, f"cell {key} identity"):
            identity = parse_cell_record(row["CELL"])
            check_cell_geometry(self.metadata, identity)
        if identity["index"] != key or identity["tract"] != self.metadata.tract:
            raise CellCoaddFormatError(
                self.path,
                f"cell index row {key} describes cell {identity['index']} of tract "
                f"{identity['tract']}",
            )
        # the inputs first: the planes with a layer per used input are sized by them
        inputs = self._read_inputs_hdu(key, int(row[hdu_column(cell_planes.INPUTS)]))
        n_used = sum(record.is_used for record in inputs)
        shapes = expected_shapes(self.metadata, identity["outer_bbox"], n_used)
        planes: dict[str, Any] = {}  # arrays, by CellCoadd field name
        columns = row.dtype.names or ()
        for spec in cell_planes.PLANES:
            column = hdu_column(spec.name)
            if spec.optional and column not in columns:  # a file before the plane
                continue
            number = int(row[column])
            if spec.per_realization and self.metadata.n_noise == 0 and number == -1:
                planes[spec.name] = np.zeros(shapes[spec.name], dtype=spec.dtype)
                continue
            if spec.optional and number == -1:  # not stored: None
                continue
            shape = shapes[spec.name]
            empty = n_used == 0  # only then may a plane be stored without pixels
            if spec.per_input and not shape[0]:  # before 1.6: one zero layer stands for none
                layer = self._read_plane(key, spec.name, number, (1, *shape[1:]), empty)
                planes[spec.name] = layer[:0]
                continue
            planes[spec.name] = self._read_plane(key, spec.name, number, shape, empty)
        with reading_errors(self.path, f"cell {key} contents"):
            common = self.metadata.cell_common  # a cell read alone describes itself
            return CellCoadd(**planes, inputs=inputs, **identity, common=common)

    def _read_plane(
        self,
        key: tuple[int, int],
        plane: str,
        number: int,
        shape: tuple[int, ...],
        empty: bool = False,
    ) -> np.ndarray:
        """The plane of ``shape`` stored in HDU ``number``; ``empty``: the cell has no
        used input, so the HDU may hold no pixels (``CCEMPTY``, format 1.6)."""
        hdu = self._hdu(number, extname(key, plane))
        with reading_errors(self.path, f"cell {key} plane {plane}"):
            dims = tuple(hdu.get_dims())
            if not dims and empty and hdu.read_header().get(EMPTY_KEY) is True:
                no_data = self.metadata.mask_bits.value("NO_DATA")
                return empty_plane(cell_planes.plane(plane), shape, no_data)
            if dims != shape:
                raise DamagedDataError(f"dimensions {dims}, expected {shape}", cell=key)
            header = hdu.read_header()
            as_bits = header.get("CCBITS") == "FLOAT32"  # files before float compression
            data = hdu.read()
            spec = cell_planes.plane(plane)
            expected = spec.dtype
            if as_bits:
                if data.dtype.kind != "i" or data.itemsize != 4 or spec.compression != "float_bits":
                    raise DamagedDataError(f"CCBITS on a {data.dtype} {plane} plane", cell=key)
                # Native byte order first, then reinterpret the bits.
                data = data.astype(np.int32, copy=False).view(np.float32)
            elif "CCNFNUM" in header:
                where = f"cell {key} plane {plane}"
                if spec.compression != "float_bits" or data.dtype.kind != "f":
                    raise CellCoaddFormatError(
                        self.path, f"{where}: CCNFNUM on a {data.dtype} plane"
                    )
                data = _restore_nonfinite(
                    data.astype(np.float32, copy=False), header, self.path, where
                )
            if (data.dtype.kind, data.itemsize) != (expected.kind, expected.itemsize):
                raise DamagedDataError(f"dtype {data.dtype}, expected {expected}", cell=key)
            return data

    def _read_inputs_hdu(self, key: tuple[int, int], number: int) -> list[InputRecord]:
        hdu = self._hdu(number, extname(key, cell_planes.INPUTS))
        with reading_errors(self.path, f"cell {key} inputs"):
            return inputs_from_array(hdu.read(), ascii_only=True)

    def read_cell_inputs(self, index: tuple[int, int]) -> list[InputRecord]:
        key, row = self._row(index)
        return self._read_inputs_hdu(key, int(row[hdu_column(cell_planes.INPUTS)]))

    def close(self) -> None:
        fits = getattr(self, "_fits", None)
        if fits is not None:
            self._opened = {}
            fits.close()
            self._fits = None
        raw = getattr(self, "_raw", None)
        if raw is not None:
            raw.close()
            self._raw = None
