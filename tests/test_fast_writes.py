"""The checksums the fast writers compute themselves are the ones FITS tools and HDF5 compute.

HDF5 chunks are stored with a Fletcher-32 computed by numpy (``hdf5_chunks``), FITS image
HDUs with DATASUM, CHECKSUM and DATACRC computed by each cell's thread (``fits_direct``);
both writers compute in threads (``parallel``) and start the write-back early
(``writeback``). Here: the checksums agree with HDF5's, fitsio's and astropy's own,
a corrupted byte is reported, files round-trip losslessly and do not depend on timing.
"""

from __future__ import annotations

import hashlib
import threading
import time
import warnings

import fitsio
import h5py
import numpy as np
import pytest
from astropy.io import fits as afits
from coadd_factory import make_patch
from hypothesis import given, settings
from hypothesis import strategies as st

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.io import api
from cellcoadd.io._files import parallel, writeback
from cellcoadd.io._fits import direct as fits_direct
from cellcoadd.io.coadd import fits_format, hdf5_chunks, hdf5_format
from cellcoadd.io.coadd.hdf5_chunks import ChunkScratch, fletcher32
from cellcoadd.model import planes as cell_planes


def _reference_fletcher32(data: bytes) -> int:
    """``H5_checksum_fletcher32`` of HDF5 (H5checksum.c), word by word."""
    sum1 = sum2 = 0
    words = len(data) // 2
    position = 0
    while words:
        block = min(words, 360)
        words -= block
        for _ in range(block):
            sum1 += (data[position] << 8) | data[position + 1]
            sum2 += sum1
            position += 2
        sum1 = (sum1 & 0xFFFF) + (sum1 >> 16)
        sum2 = (sum2 & 0xFFFF) + (sum2 >> 16)
    if len(data) % 2:
        sum1 += data[position] << 8
        sum2 += sum1
        sum1 = (sum1 & 0xFFFF) + (sum1 >> 16)
        sum2 = (sum2 & 0xFFFF) + (sum2 >> 16)
    sum1 = (sum1 & 0xFFFF) + (sum1 >> 16)
    sum2 = (sum2 & 0xFFFF) + (sum2 >> 16)
    return (sum2 << 16) | sum1


@settings(max_examples=200, deadline=None)
@given(st.binary(min_size=0, max_size=20000))
def test_fletcher32_matches_the_reference(data):
    assert fletcher32(data) == _reference_fletcher32(data)


@pytest.mark.parametrize("size", [0, 1, 2, 3, 8191, 8192, 8193, 16384, 24577])
@pytest.mark.parametrize("byte", [0x00, 0x01, 0xFF])
def test_fletcher32_constant_data(size, byte):
    # all-ones words make sums that are multiples of 65535: folded to 0xFFFF, never 0
    data = bytes([byte]) * size
    assert fletcher32(data) == _reference_fletcher32(data)


def test_fletcher32_is_what_hdf5_stores(tmp_path):
    """Chunks HDF5's own filter wrote end with the checksum ``fletcher32`` computes."""
    rng = np.random.default_rng(1)
    arrays = {
        "image": rng.normal(size=(250, 250)).astype(np.float32),
        "noise": rng.normal(size=(3, 250, 250)).astype(np.float32),
        "psf": rng.normal(size=(35, 35)),
        "mask": rng.integers(0, 2**31, size=(17, 13), dtype=np.int32),
        "odd": np.arange(11, dtype=np.uint8),
        "big": rng.integers(0, 2**16, size=(2**22 + 3,), dtype=np.uint16),  # two slabs
        "ones": np.full(4097, 0xFFFF, dtype=np.uint16),
    }
    path = tmp_path / "filtered.h5"
    with h5py.File(path, "w") as h5:
        for name, data in arrays.items():
            h5.create_dataset(name, data=data, chunks=data.shape, fletcher32=True)
    with h5py.File(path, "r") as h5:
        for name, data in arrays.items():
            _, stored = h5[name].id.read_direct_chunk((0,) * data.ndim)
            assert stored[:-4] == data.tobytes()
            assert int.from_bytes(stored[-4:], "little") == fletcher32(data), name
            assert bytes(ChunkScratch().chunk(data)) == stored, name


def test_written_hdf5_chunks_are_those_hdf5_would_write(tmp_path):
    """Every stored chunk of a written file is byte for byte what HDF5's filter stores."""
    patch = make_patch(seed=3, psf_corners=True, psf_phase=True)  # every plane
    path = tmp_path / "patch.h5"
    api.write(patch, path)
    reference = tmp_path / "reference.h5"
    with h5py.File(path, "r") as h5, h5py.File(reference, "w") as ref:
        for index in patch.cells:
            group = h5["cells"][hdf5_format.group_name(index)]
            for name in cell_planes.cell_objects():
                dataset = group[name]
                if dataset.size == 0:
                    continue
                assert dataset.fletcher32 and dataset.chunks == dataset.shape
                _, stored = dataset.id.read_direct_chunk((0,) * dataset.ndim)
                data = dataset[()]
                copy = ref.create_dataset(
                    f"{index}/{name}", data=data, chunks=data.shape, fletcher32=True
                )
                assert copy.id.read_direct_chunk((0,) * data.ndim)[1] == stored
    assert api.read(path).equals(patch)


@pytest.mark.parametrize("compression", [None, "lossless"])
def test_hdf5_flipped_byte_in_any_plane_is_reported(tmp_path, compression):
    patch = make_patch(seed=4, psf_corners=True, psf_phase=True)  # every plane
    path = tmp_path / "patch.h5"
    api.write(patch, path, compression=compression)
    raw = path.read_bytes()
    index = next(iter(patch.cells))
    for plane in cell_planes.cell_objects():
        with h5py.File(path, "r") as h5:
            info = h5[f"cells/{hdf5_format.group_name(index)}/{plane}"].id.get_chunk_info(0)
        for offset in (info.byte_offset, info.byte_offset + info.size // 2):
            damaged = bytearray(raw)
            damaged[offset] ^= 0x10
            path.write_bytes(bytes(damaged))
            with pytest.raises(CellCoaddFormatError, match="cell"):
                api.read_cell(path, index)
        path.write_bytes(raw)
    assert api.read(path).equals(patch)


def test_fits_checksums_verified_by_fitsio_and_astropy(tmp_path):
    patch = make_patch(seed=5)
    path = tmp_path / "patch.fits"
    api.write(patch, path)
    with fitsio.FITS(str(path)) as fits:
        for hdu in fits:
            hdu.verify_checksum()  # raises on a wrong CHECKSUM or DATASUM
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # astropy warns about failed checksums
        with afits.open(path, checksum=True) as hdus:
            for hdu in hdus:
                hdu.data  # noqa: B018 - reading the data verifies DATASUM
    # a flipped pixel bit: every verifier reports it
    index = next(iter(patch.cells))
    with fitsio.FITS(str(path)) as fits:
        offsets = fits[fits_format.extname(index, "noise")].get_offsets()
    damaged = bytearray(path.read_bytes())
    damaged[(offsets["data_start"] + offsets["data_end"]) // 2 + 1] ^= 0x04
    path.write_bytes(bytes(damaged))
    with fitsio.FITS(str(path)) as fits, pytest.raises(ValueError, match="checksum failed"):
        fits[fits_format.extname(index, "noise")].verify_checksum()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with afits.open(path, checksum=True) as hdus:
            hdus[fits_format.extname(index, "noise")].data  # noqa: B018
    assert any("Datasum verification failed" in str(w.message) for w in caught)
    with pytest.raises(CellCoaddFormatError, match="checksum"):
        api.read_cell(path, index)


@pytest.mark.parametrize("name", ["patch.fits", "patch.h5"])
def test_files_do_not_depend_on_the_threads_timing(tmp_path, monkeypatch, name):
    """Slow, uneven threads (cells prepared late, out of order) give the same bytes."""
    patch = make_patch(seed=6)
    monkeypatch.setattr(hdf5_format, "_BATCH", 2)  # several batches
    api.write(patch, tmp_path / f"fast-{name}")

    def slowly(function):
        def slow(*args, **kwargs):
            time.sleep(0.001 * (threading.get_ident() % 3 + hash(id(args[0])) % 3))
            return function(*args, **kwargs)

        return slow

    monkeypatch.setattr(fits_direct, "image_data", slowly(fits_direct.image_data))
    monkeypatch.setattr(hdf5_format, "_prepare_batch", slowly(hdf5_format._prepare_batch))
    api.write(patch, tmp_path / f"slow-{name}")
    digests = {hashlib.sha256(p.read_bytes()).digest() for p in tmp_path.iterdir()}
    assert len(digests) == 1
    assert api.read(tmp_path / f"slow-{name}").equals(patch)


def test_map_in_threads_order_and_errors():
    threads_seen: set[int] = set()

    def square(item: int) -> int:
        threads_seen.add(threading.get_ident())
        time.sleep(0.001 * (item % 3))
        return item * item

    assert parallel.map_in_threads(square, range(40), threads=2) == [i * i for i in range(40)]
    assert parallel.map_in_threads(square, [], threads=2) == []
    done: list[int] = []

    def failing(item: int) -> int:
        if item == 5:
            raise ValueError("bad item")
        time.sleep(0.002)
        done.append(item)
        return item

    with pytest.raises(ValueError, match="bad item"):
        parallel.map_in_threads(failing, range(200), threads=2)
    assert len(done) < 199  # the items after the failure were skipped
    finished = len(done)
    time.sleep(0.05)
    assert len(done) == finished  # and no thread runs on after the call


def test_early_writeback_starts_and_stops(tmp_path, monkeypatch):
    calls: list[int] = []
    monkeypatch.setattr(writeback, "STEP", 1 << 16)
    monkeypatch.setattr(writeback, "_START_WRITEBACK", lambda fd, *args: calls.append(fd) or 0)
    path = tmp_path / "growing.bin"
    with writeback.EarlyWriteback(path) as watcher:
        time.sleep(0.02)  # the file does not exist yet: nothing to do
        with open(path, "wb") as stream:
            for _ in range(8):
                stream.write(bytes(1 << 16))
                stream.flush()
                time.sleep(0.02)
    assert calls, "write-back was never started"
    assert watcher._thread is not None and not watcher._thread.is_alive()
    assert path.stat().st_size == 8 << 16


def test_hdf5_dataset_maker_objects_match_h5py(tmp_path):
    """Objects made by ObjectMaker read back as h5py-made ones do (types, attributes)."""
    path = tmp_path / "made.h5"
    data = np.arange(12, dtype=np.float32).reshape(3, 4)
    table = np.zeros(2, dtype=[("visit", "<i8"), ("band", "S3")])
    table["band"] = [b"r", b"i\xc3\xa9"]
    with h5py.File(path, "w", libver=("v110", "v110")) as h5:
        maker = hdf5_chunks.ObjectMaker(compress=False)
        group = maker.group(h5.id, "g")
        maker.attributes(group, [("text", "abc"), ("number", 3), ("value", 1.5)])
        maker.dataset(group, "data", data, [("plane", "image")] + [(f"K{n}", n) for n in range(12)])
        maker.dataset(group, "table", table)
        maker.dataset(group, "empty", np.zeros(0, dtype=np.float32))
        for number in range(3):  # copies of one template, and one made directly
            maker.dataset(group, f"copy{number}", data, [("plane", "image")], repeated=True)
        maker.dataset(group, "listed", data, [("bits", [1, 2])], repeated=True)
    with h5py.File(path, "r") as h5:
        group = h5["g"]
        assert dict(group.attrs) == {"text": b"abc", "number": 3, "value": 1.5}
        assert isinstance(group.attrs["text"], np.bytes_)
        assert group.attrs["number"].dtype == np.int64
        assert np.array_equal(group["data"][()], data) and group["data"].fletcher32
        assert group["data"].attrs["plane"] == b"image" and group["data"].attrs["K11"] == 11
        assert np.array_equal(group["table"][()], table)
        assert group["empty"].shape == (0,) and group["empty"].chunks is None
        assert group["data"].id.get_create_plist().get_obj_track_times() == 0
        for number in range(3):
            copy = group[f"copy{number}"]
            assert np.array_equal(copy[()], data) and dict(copy.attrs) == {"plane": b"image"}
            assert copy.fletcher32 and copy.chunks == data.shape
        assert list(group["listed"].attrs["bits"]) == [1, 2]


def test_wcs_records_from_wcslib_text_equal_astropy_headers():
    """The cached path of ``wcs_to_record`` (used once per write) gives the same records."""
    from astropy.wcs import WCS, Sip

    from cellcoadd.model.wcs_codec import wcs_to_record

    patch = make_patch(seed=7)
    zpn = WCS(naxis=2)
    zpn.wcs.ctype = ["RA---ZPN", "DEC--ZPN"]
    zpn.wcs.set_pv([(2, 1, 1.0), (2, 3, 0.3)])
    zpn.wcs.crval, zpn.wcs.cdelt, zpn.wcs.crpix = [10, -20], [-1e-4, 1e-4], [1.5, 2.5]
    dated = WCS(naxis=2)
    dated.wcs.ctype = ["GLON-CAR", "GLAT-CAR"]
    dated.wcs.dateobs, dated.wcs.mjdref = "2020-01-01T00:00:00", [1, 0]
    sip = WCS(naxis=2)
    sip.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"]
    sip.wcs.crval, sip.wcs.cd, sip.wcs.crpix = [1, 2], [[1e-4, 0], [0, 1e-4]], [10, 10]
    a = np.array([[0, 0, 1e-6], [0, 1e-7, 0], [2e-6, 0, 0]])
    sip.sip = Sip(a, a.T.copy(), None, None, sip.wcs.crpix)
    cache: dict = {}
    for wcs in [*(cell.wcs for cell in patch.values()), zpn, dated, sip]:
        for _ in range(2):  # parsed, then from the cache
            assert wcs_to_record(wcs, card_values=cache) == wcs_to_record(wcs)


@pytest.mark.parametrize("name", ["patch.fits", "patch.h5"])
def test_files_written_without_threads_are_the_same(tmp_path, monkeypatch, name):
    patch = make_patch(seed=8, n_noise=2)
    api.write(patch, tmp_path / f"thread-{name}")
    monkeypatch.setattr(parallel, "THREADS", 1)
    monkeypatch.setattr(writeback, "_START_WRITEBACK", None)
    api.write(patch, tmp_path / f"sync-{name}")
    assert (tmp_path / f"thread-{name}").read_bytes() == (tmp_path / f"sync-{name}").read_bytes()
