"""Damaged files: every reader either refuses with CellCoaddFormatError or returns the
original data, never another exception, never a hang.

Random damage (hypothesis): truncations, bit flips, overwritten, zeroed, dropped,
duplicated or swapped byte blocks, in coadd files (FITS, tile-compressed FITS, HDF5) and
exposure files. Structured damage: HDUs or HDF5 objects reordered, swapped, replaced or
given another version, and files of the other kinds. ``-m slow`` runs a long fuzz.
"""

from __future__ import annotations

import os
import threading
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import fitsio
import galsim
import h5py
import numpy as np
import pytest
from coadd_factory import MEDIUM, SMALL, make_patch
from exposure_factory import make_wcs
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.geometry.box import Box
from cellcoadd.io import api
from cellcoadd.io._fits.checksums import DATACRC
from cellcoadd.io.coadd import hdf5_format
from cellcoadd.io.coadd.fits_format import extname
from cellcoadd.io.exposures.exposure_io import read_exposure, write_exposure
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.psf_profiles import VaryingPsf

#: Longest a read of these small files may take before it counts as a hang, seconds.
DEADLINE = 30.0
KINDS = ("coadd.fits", "coadd.fits.fz", "coadd.h5", "exposure.fits")
BLOCK = 2880


# ------------------------------------------------------------------------------ originals


def small_exposure() -> Exposure:
    """An exposure with every optional part: mask bits, variance plane, varying PSF."""
    shape = (40, 50)
    rng = np.random.default_rng(8)
    bits = MaskBits(bits={**MaskBits().bits, "ODD": 11})
    mask = np.zeros(shape, dtype=np.int32)
    mask[3, 4] = bits.value("BAD") | bits.value("ODD")
    image = rng.standard_normal(shape).astype(np.float32)
    image[3, 4] = np.inf
    psf = VaryingPsf(
        base=galsim.Moffat(beta=3.5, fwhm=0.9),
        x0=25.0,
        y0=20.0,
        radius=40.0,
        dilation=((2, 0, 0.01),),
        g1=((1, 0, 0.01),),
        g2=((0, 1, -0.01),),
    )
    return Exposure(
        image=image,
        wcs=make_wcs((10.0, 20.0), shape, 0.26, rotation_deg=17.0, sip=True),
        variance=rng.uniform(0.9, 1.1, shape),
        psf=psf,
        visit=4321,
        detector=12,
        band="i",
        zero_point=31.25,
        mask=mask,
        mask_bits=bits,
        valid_box=Box(x_start=1, x_stop=49, y_start=2, y_stop=40),
    )


def exposures_equal(first: Exposure, second: Exposure) -> bool:
    """Bitwise equal planes (NaNs compared by position) and equal metadata and PSF."""

    def same(a: Any, b: Any) -> bool:
        if isinstance(a, float) or isinstance(b, float):
            return a == b
        return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)

    header_a = first.wcs.to_header(relax=True)
    header_b = second.wcs.to_header(relax=True)
    return (
        same(first.image, second.image)
        and same(first.mask, second.mask)
        and same(first.variance, second.variance)
        and (first.key, first.band) == (second.key, second.band)
        and first.zero_point == second.zero_point
        and first.valid_box == second.valid_box
        and first.mask_bits == second.mask_bits
        and first.psf == second.psf
        and header_a.tostring() == header_b.tostring()
    )


@pytest.fixture(scope="module")
def originals(tmp_path_factory) -> dict[str, tuple[bytes, Any]]:
    """Bytes and contents of one small file of each kind."""
    directory = tmp_path_factory.mktemp("originals")
    patch = make_patch(SMALL, seed=21, n_noise=1, psf_size=3, empty=((0, 0),))
    out: dict[str, tuple[bytes, Any]] = {}
    for name in KINDS[:3]:
        compression = "lossless" if name.endswith((".fz", ".h5")) else None
        api.write(patch, directory / name, compression=compression)
        out[name] = ((directory / name).read_bytes(), patch)
    write_exposure(small_exposure(), directory / KINDS[3])
    out[KINDS[3]] = ((directory / KINDS[3]).read_bytes(), read_exposure(directory / KINDS[3]))
    return out


# ------------------------------------------------------------------------ reading safely


def read_within_deadline(read: Callable[[Path], Any], path: Path) -> dict[str, Any]:
    """``{"value": ...}`` or ``{"error": ...}`` of ``read(path)``; fails the test on a hang."""
    outcome: dict[str, Any] = {}

    def run() -> None:
        try:
            outcome["value"] = read(path)
        except BaseException as err:  # judged by the caller
            outcome["error"] = err

    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    worker.join(DEADLINE)
    if worker.is_alive():
        pytest.fail(f"reading {path} did not finish within {DEADLINE} s")
    return outcome


def reader_of(kind: str) -> tuple[Callable[[Path], Any], Callable[[Any, Any], bool]]:
    if kind.startswith("exposure"):
        return read_exposure, exposures_equal
    return api.read, lambda read_back, patch: read_back.equals(patch)


def check_damaged(path: Path, kind: str, original: Any) -> str:
    """Read ``path``; 'refused' or 'intact', failing on anything else."""
    read, equal = reader_of(kind)
    outcome = read_within_deadline(read, path)
    if "error" in outcome:
        error = outcome["error"]
        if not isinstance(error, CellCoaddFormatError):
            raise AssertionError(f"{type(error).__name__} instead of a format error") from error
        assert error.path == os.fspath(path), "the error must name the file"
        assert error.problem.strip(), "the error must say what is wrong"
        return "refused"
    assert equal(outcome["value"], original), "a damaged file was read as different data"
    return "intact"


# ------------------------------------------------------------------------- random damage


def damage(data: bytes, draw: Callable[[st.SearchStrategy], Any]) -> bytes:
    """One random kind of damage to ``data`` (hypothesis ``draw`` picks the details)."""
    size = len(data)
    kind = draw(st.sampled_from(["truncate", "flip", "overwrite", "zero", "drop", "dup", "swap"]))
    offset = draw(st.integers(0, size - 1))
    if kind == "truncate":
        return data[:offset]
    if kind == "flip":
        changed = bytearray(data)
        changed[offset] ^= 1 << draw(st.integers(0, 7))
        return bytes(changed)
    length = draw(st.sampled_from([1, 8, 80, BLOCK, 3 * BLOCK]))
    if kind == "overwrite":
        noise = draw(st.binary(min_size=length, max_size=length))
        return data[:offset] + noise + data[offset + length :]
    if kind == "zero":
        return data[:offset] + bytes(length) + data[offset + length :]
    # whole FITS blocks: what a bad copy or a misbehaving tool does
    blocks = size // BLOCK
    first = draw(st.integers(0, max(0, blocks - 1))) * BLOCK
    second = draw(st.integers(0, max(0, blocks - 1))) * BLOCK
    if kind == "drop":
        return data[:first] + data[first + BLOCK :]
    if kind == "dup":
        return data[: first + BLOCK] + data[first : first + BLOCK] + data[first + BLOCK :]
    low, high = sorted((first, second))
    if low == high:
        return data[:low] + data[low + BLOCK :]
    return (
        data[:low]
        + data[high : high + BLOCK]
        + data[low + BLOCK : high]
        + data[low : low + BLOCK]
        + data[high + BLOCK :]
    )


def fuzz_once(tmp_path_factory, originals, kind: str, draw) -> str:
    raw, original = originals[kind]
    damaged = damage(raw, draw)
    path = tmp_path_factory.getbasetemp() / f"fuzz-{kind}"
    path.write_bytes(damaged)
    return check_damaged(path, kind, original)


_FUZZ = dict(
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=60, derandomize=True, **_FUZZ)
@given(data=st.data())
def test_random_damage_is_refused_or_harmless(tmp_path_factory, originals, kind, data):
    fuzz_once(tmp_path_factory, originals, kind, data.draw)


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=1500, **_FUZZ)
@given(data=st.data())
def test_random_damage_long_run(tmp_path_factory, originals, kind, data):
    fuzz_once(tmp_path_factory, originals, kind, data.draw)


def data_units(raw: bytes, path: Path) -> list[tuple[int, int]]:
    """Byte ranges of the data units of a FITS file."""
    path.write_bytes(raw)
    with fitsio.FITS(str(path)) as fits:
        return [(h.get_offsets()["data_start"], h.get_offsets()["data_end"]) for h in fits]


def swap_blocks(raw: bytes, first: int, second: int) -> bytes:
    """``raw`` with the 2880-byte blocks at offsets ``first < second`` swapped."""
    assert raw[first : first + BLOCK] != raw[second : second + BLOCK], "identical blocks"
    return (
        raw[:first]
        + raw[second : second + BLOCK]
        + raw[first + BLOCK : second]
        + raw[first : first + BLOCK]
        + raw[second + BLOCK :]
    )


@pytest.mark.parametrize("kind", ["coadd.fits", "coadd.fits.fz", "exposure.fits"])
def test_block_swap_inside_a_fits_data_unit(tmp_path, originals, kind):
    """CHECKSUM/DATASUM are sums of 32-bit words, blind to their order; DATACRC is not."""
    raw, original = originals[kind]
    start, stop = max(data_units(raw, tmp_path / "probe.fits"), key=lambda u: u[1] - u[0])
    assert stop - start >= 2 * BLOCK
    (tmp_path / kind).write_bytes(swap_blocks(raw, start, stop - BLOCK))
    assert check_damaged(tmp_path / kind, kind, original) == "refused"


@pytest.mark.parametrize("name", ["patch.fits", "patch.fits.fz"])
def test_read_cell_catches_a_block_swap_in_its_own_planes_only(tmp_path, name):
    patch = make_patch(MEDIUM, seed=5, n_noise=1)
    path = tmp_path / name
    api.write(patch, path)
    raw = path.read_bytes()
    damaged, intact = list(patch)[:2]
    with fitsio.FITS(str(path)) as fits:
        hdu = fits[extname(damaged, "noise")]
        start, stop = hdu.get_offsets()["data_start"], hdu.get_offsets()["data_end"]
    assert stop - start >= 2 * BLOCK
    path.write_bytes(swap_blocks(raw, start, stop - BLOCK))
    with pytest.raises(CellCoaddFormatError, match="DATACRC"):
        api.read_cell(path, damaged)
    assert api.read_cell(path, intact).equals(patch[intact])
    with fitsio.FITS(str(path)) as fits:  # the FITS checksums cannot see a reordering
        fits[extname(damaged, "noise")].verify_checksum()


def strip_datacrc(raw: bytes, path: Path) -> bytes:
    """``raw`` as written before DATACRC existed: no DATACRC card, valid checksums."""
    path.write_bytes(raw)
    with fitsio.FITS(str(path), "rw") as fits:
        for hdu in fits:
            hdu.delete_key(DATACRC)
            hdu.write_checksum()
    stripped = path.read_bytes()
    assert len(stripped) == len(raw) and b"DATACRC" not in stripped
    return stripped


@pytest.mark.parametrize("kind", ["coadd.fits", "coadd.fits.fz", "exposure.fits"])
def test_every_hdu_carries_the_crc_of_its_data_unit(tmp_path, originals, kind):
    raw, _ = originals[kind]
    path = tmp_path / kind
    path.write_bytes(raw)
    with fitsio.FITS(str(path)) as fits:
        for hdu in fits:
            offsets = hdu.get_offsets()
            data = raw[offsets["data_start"] : offsets["data_end"]]
            assert hdu.read_header()[DATACRC] == zlib.crc32(data), hdu.get_extname()


@pytest.mark.parametrize("kind", ["coadd.fits", "coadd.fits.fz", "exposure.fits"])
def test_files_without_datacrc_still_read(tmp_path, originals, kind):
    raw, original = originals[kind]
    old = strip_datacrc(raw, tmp_path / "probe.fits")
    (tmp_path / kind).write_bytes(old)
    assert check_damaged(tmp_path / kind, kind, original) == "intact"
    if kind.startswith("coadd"):
        first = next(iter(original))
        assert api.read_cell(tmp_path / kind, first).equals(original[first])


@pytest.mark.parametrize("kind", ["coadd.fits", "coadd.fits.fz", "exposure.fits"])
def test_a_wrong_datacrc_under_valid_checksums_is_refused(tmp_path, originals, kind):
    raw, original = originals[kind]
    path = tmp_path / kind
    path.write_bytes(raw)
    with fitsio.FITS(str(path), "rw") as fits:
        hdu = fits[-1]
        hdu.write_key(DATACRC, (hdu.read_header()[DATACRC] + 1) % 2**32)
        hdu.write_checksum()
    assert check_damaged(path, kind, original) == "refused"


# ---------------------------------------------------------------------- structured damage


def fits_hdus(raw: bytes, path: Path) -> list[bytes]:
    """The byte ranges of every HDU of a FITS file."""
    path.write_bytes(raw)
    with fitsio.FITS(str(path)) as fits:
        offsets = [hdu.get_offsets() for hdu in fits]
    return [raw[o["header_start"] : o["data_end"]] for o in offsets]


@pytest.mark.parametrize("kind", ["coadd.fits", "coadd.fits.fz", "exposure.fits"])
def test_reordered_or_missing_hdus(tmp_path, originals, kind):
    raw, original = originals[kind]
    hdus = fits_hdus(raw, tmp_path / "probe.fits")
    path = tmp_path / kind
    n = len(hdus)
    orders = [[0, 2, 1, *range(3, n)], [*range(n - 2), n - 1, n - 2], [0, *range(2, n)]]
    if n > 8:  # a coadd: swap planes of one cell, and the same plane of two cells
        orders += [[0, 1, 2, 4, 3, *range(5, n)], [*range(3), 9, *range(4, 9), 3, *range(10, n)]]
    outcomes = []
    for order in orders:
        path.write_bytes(b"".join(hdus[i] for i in order))
        outcomes.append(check_damaged(path, kind, original))
    if kind.startswith("coadd"):
        assert set(outcomes) == {"refused"}  # HDU numbers are part of the layout
    else:
        assert outcomes[-1] == "refused"  # exposures find HDUs by name; one is missing


def rewrite_hdf5(source: bytes, path: Path, edit: Callable[[h5py.File], None]) -> None:
    path.write_bytes(source)
    with h5py.File(path, "r+") as h5:
        edit(h5)


def _swap(h5: h5py.File, first: str, second: str) -> None:
    h5.move(first, "swap-tmp")
    h5.move(second, first)
    h5.move("swap-tmp", second)


def _replace(h5: h5py.File, name: str, data: np.ndarray, **options: Any) -> None:
    del h5[name]
    h5.create_dataset(name, data=data, **options)


def test_hdf5_swapped_or_replaced_objects(tmp_path, originals):
    raw, original = originals["coadd.h5"]
    a, b = (f"cells/{hdf5_format.group_name(index)}" for index in list(original)[:2])
    shape = original[next(iter(original))].shape
    edits: dict[str, Callable[[h5py.File], None]] = {
        "swapped cells": lambda h5: _swap(h5, a, b),
        "float mask": lambda h5: _replace(h5, f"{a}/mask", np.zeros(shape, np.float32)),
        "noise of the wrong size": lambda h5: _replace(h5, f"{a}/noise", np.zeros((5, 2, 2))),
        "image without checksum": lambda h5: _replace(h5, f"{a}/image", h5[f"{b}/image"][()]),
        "version 2": lambda h5: h5.attrs.__setitem__("format_version", np.bytes_("2.0")),
        "version garbage": lambda h5: h5.attrs.__setitem__("format_version", np.bytes_("x.y")),
        "other kind": lambda h5: h5.attrs.__setitem__("cellcoadd_format", np.bytes_("other")),
        "no cells group": lambda h5: h5.__delitem__("cells"),
    }
    path = tmp_path / "edited.h5"
    for label, edit in edits.items():
        rewrite_hdf5(raw, path, edit)
        assert check_damaged(path, "coadd.h5", original) == "refused", label


def test_hdf5_swapped_planes_are_refused(tmp_path, originals):
    raw, original = originals["coadd.h5"]
    cell = f"cells/{hdf5_format.group_name(next(iter(original)))}"
    path = tmp_path / "planes.h5"
    rewrite_hdf5(raw, path, lambda h5: _swap(h5, f"{cell}/image", f"{cell}/variance"))
    assert check_damaged(path, "coadd.h5", original) == "refused"


def _structure_mutation(h5: h5py.File, rng: np.random.Generator, kind: str, other: Path) -> None:
    """One structure-level edit of a cellcoadd HDF5 file (links, deleted groups, resized or
    unallocated datasets), on a random cell and plane."""
    cells = sorted(h5["cells"])
    first, second = (str(c) for c in rng.choice(cells, 2, replace=False))
    plane = str(rng.choice(["image", "mask", "variance", "mfrac", "noise", "psf", "inputs"]))
    name, source = f"cells/{first}/{plane}", f"/cells/{second}/{plane}"
    if kind == "soft link":
        del h5[name]
        h5[name] = h5py.SoftLink(source)
    elif kind == "hard link":
        del h5[name]
        h5[name] = h5[source]
    elif kind == "external link":
        del h5[f"cells/{first}"]
        h5[f"cells/{first}"] = h5py.ExternalLink(str(other), f"/cells/{first}")
    elif kind == "deleted group":
        del h5[f"cells/{first}"]
    elif kind in ("resized", "unallocated"):
        dataset = h5[name]
        shape = list(dataset.shape) or [1]
        if kind == "resized":
            shape[0] += int(rng.integers(1, 1000))
        data, dtype = dataset[()], dataset.dtype
        del h5[name]
        made = h5.create_dataset(
            name, shape=tuple(shape), dtype=dtype, chunks=tuple(shape), fletcher32=True
        )
        if kind == "resized" and data.size:
            made[tuple(slice(0, n) for n in data.shape)] = data
        made.attrs["plane"] = np.bytes_(plane)


@pytest.mark.parametrize(
    "kind", ["soft link", "hard link", "external link", "deleted group", "resized", "unallocated"]
)
def test_hdf5_structure_mutations_are_refused(tmp_path, originals, kind):
    raw, original = originals["coadd.h5"]
    other = tmp_path / "other.h5"
    other.write_bytes(raw)
    path = tmp_path / "mutated.h5"
    rng = np.random.default_rng(zlib.crc32(kind.encode()))
    for _ in range(8):
        rewrite_hdf5(raw, path, lambda h5: _structure_mutation(h5, rng, kind, other))
        assert check_damaged(path, "coadd.h5", original) == "refused", kind
        with pytest.raises(CellCoaddFormatError):
            api.read(path, verify=False)


def _set_card(raw: bytes, start: int, key: bytes, value: int) -> bytes:
    """``raw`` with the integer card ``key`` of the header starting at ``start`` set."""
    position = raw.index(key.ljust(8) + b"=", start)
    card = f"{key.decode():<8}= {value:>20}".ljust(80).encode("ascii")
    return raw[:position] + card + raw[position + 80 :]


@pytest.mark.parametrize("kind", ["coadd.fits", "coadd.fits.fz", "exposure.fits"])
def test_fits_headers_declaring_other_shapes_are_refused(tmp_path, originals, kind):
    """A header whose NAXISn (ZNAXISn when tile compressed) disagrees with the data, with
    checksums off for the coadd: refused, never read as another shape."""
    raw, original = originals[kind]
    probe = tmp_path / kind
    probe.write_bytes(raw)
    with fitsio.FITS(str(probe)) as fits:
        headers = [hdu.get_offsets()["header_start"] for hdu in fits]
        names = [hdu.get_extname() for hdu in fits]
    key = b"ZNAXIS1" if kind.endswith(".fz") else b"NAXIS1"
    targets = [i for i, n in enumerate(names) if n.endswith(("_PSF", "_MASK")) or n == "MASK"]
    path = tmp_path / f"shaped-{kind}"
    for index in targets[:6]:
        for value in (1, 7, 4001):
            hdu_key = b"NAXIS1" if names[index].endswith("_PSF") else key
            path.write_bytes(_set_card(raw, headers[index], hdu_key, value))
            assert check_damaged(path, kind, original) == "refused", (names[index], value)
            if kind.startswith("coadd"):
                with pytest.raises(CellCoaddFormatError):
                    api.read(path, verify=False)


def test_fits_wrong_version_keywords(tmp_path, originals):
    for kind, keyword, hdu in (
        ("coadd.fits", "CCVERS", 0),
        ("coadd.fits", "CCFORMAT", 0),
        ("exposure.fits", "CCFORMAT", 0),
    ):
        raw, original = originals[kind]
        for value in ("2.0", "x.y", "cellcoadd-other"):
            path = tmp_path / kind
            path.write_bytes(raw)
            with fitsio.FITS(str(path), "rw") as fits:
                fits[hdu].write_key(keyword, value)
                fits[hdu].write_checksum()  # valid checksums: only the content is wrong
            assert check_damaged(path, kind, original) == "refused", (kind, keyword, value)


def test_a_damaged_file_does_not_spoil_later_reads(tmp_path, originals):
    """CFITSIO keeps error messages in one process-wide stack, and fitsio cannot decode
    the binary junk a damaged header leaves there: the next read of an intact file used
    to fail. Here the second header block of a cell HDU is lost, so CFITSIO parses pixel
    data as header cards."""
    raw, original = originals["coadd.fits.fz"]
    hdus = fits_hdus(raw, tmp_path / "probe.fits")
    long_header = next(h for h in hdus if h.index(b"END" + b" " * 77) >= BLOCK)
    second_block = raw.index(long_header) + BLOCK
    damaged = tmp_path / "damaged.fits.fz"
    damaged.write_bytes(raw[:second_block] + raw[second_block + BLOCK :])
    intact = tmp_path / "intact.fits.fz"
    intact.write_bytes(raw)
    (tmp_path / "exposure.fits").write_bytes(originals["exposure.fits"][0])
    for _ in range(2):
        assert check_damaged(damaged, "coadd.fits.fz", original) == "refused"
        assert api.read(intact).equals(original)
        assert exposures_equal(
            read_exposure(tmp_path / "exposure.fits"), originals["exposure.fits"][1]
        )


def test_files_of_another_kind(tmp_path, originals):
    for kind in KINDS:
        (tmp_path / kind).write_bytes(originals[kind][0])
    cases = [
        (api.read, tmp_path / "exposure.fits"),
        (read_exposure, tmp_path / "coadd.fits"),
        (read_exposure, tmp_path / "coadd.fits.fz"),
        (read_exposure, tmp_path / "coadd.h5"),
    ]
    (tmp_path / "directory.fits").mkdir()
    (tmp_path / "directory.h5").mkdir()
    cases += [(api.read, tmp_path / "directory.fits"), (api.read, tmp_path / "directory.h5")]
    cases += [(read_exposure, tmp_path / "directory.fits")]
    for read, path in cases:
        outcome = read_within_deadline(read, path)
        error = outcome.get("error")
        assert isinstance(error, CellCoaddFormatError), (read.__name__, path, outcome)
        assert error.path == str(path)
