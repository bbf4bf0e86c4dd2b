"""Storage round trips, corruption handling and atomic writes (FITS and HDF5)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import fitsio
import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from coadd_factory import (
    SMALL,
    assert_same,
    make_metadata,
    make_patch,
    make_records,
    random_float_bits,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from kill_writer import kill_mid_write

from cellcoadd.cli.storage import convert_command, info_command, schemas_command
from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.io import api
from cellcoadd.io.coadd import fits_format, format_version, hdf5_format
from cellcoadd.model import planes as cell_planes
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.patch_coadd import FORMAT_VERSION, PatchCoadd

NAMES = ["patch.fits", "patch.fits.fz", "patch.h5", "patch.hdf5"]
LAYOUTS = [(name, comp) for name in NAMES for comp in (None, "lossless")]


@pytest.fixture(scope="module")
def patch() -> PatchCoadd:
    return make_patch(seed=1, empty=((1, 2),))


# ------------------------------------------------------------------------------ round trips


@settings(
    max_examples=15,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_noise=st.sampled_from([0, 1, 3]),
    psf_size=st.sampled_from([3, 5, 7]),
    band=st.sampled_from(["r", "y\u00b2", "H\u03b1 narrow", "z\u0301", 'a"b\\c']),
    patch_index=st.sampled_from([(0, 0), (1, 1), (2, 0)]),
    layout=st.sampled_from(LAYOUTS),
    n_empty=st.integers(0, 3),
    n_missing=st.integers(0, 2),
)
def test_round_trip_random_patches(
    tmp_path_factory, seed, n_noise, psf_size, band, patch_index, layout, n_empty, n_missing
):
    rng = np.random.default_rng(seed)
    all_indices = make_metadata(patch=patch_index).all_cell_indices
    picked = rng.permutation(len(all_indices))
    empty = tuple(all_indices[i] for i in picked[:n_empty])
    missing = tuple(all_indices[i] for i in picked[n_empty : n_empty + n_missing])
    original = make_patch(
        seed=seed,
        n_noise=n_noise,
        psf_size=psf_size,
        band=band,
        patch=patch_index,
        empty=empty,
        missing=missing,
    )
    name, compression = layout
    path = tmp_path_factory.mktemp("rt") / name
    api.write(original, path, compression=compression)
    assert_same(api.read(path), original)
    with api.open(path) as coadd_file:
        assert coadd_file.metadata == original.metadata
        assert coadd_file.cell_indices == list(original.cells)
        for index, cell in original.cells.items():
            assert coadd_file.read_cell(index).equals(cell)
    first = next(iter(original.cells))
    assert api.read_cell(path, first).equals(original[first])


@pytest.mark.parametrize(("name", "compression"), LAYOUTS)
def test_round_trip_every_layout_and_convert_back(tmp_path, patch, name, compression):
    path = tmp_path / name
    api.write(patch, path, compression=compression)
    assert_same(api.read(path), patch)
    other = "other.h5" if name.startswith("patch.fits") else "other.fits"
    api.convert(path, tmp_path / other, compression="lossless")
    api.convert(tmp_path / other, tmp_path / ("back-" + name), compression=compression)
    assert_same(api.read(tmp_path / ("back-" + name)), patch)


def test_k0_has_no_noise_hdu_and_round_trips(tmp_path):
    original = make_patch(seed=4, n_noise=0)
    for name in ("k0.fits", "k0.h5"):
        api.write(original, tmp_path / name)
        assert_same(api.read(tmp_path / name), original)
    with fitsio.FITS(str(tmp_path / "k0.fits")) as fits:
        names = {fits[i].get_extname() for i in range(len(fits))}
    assert not any(n.endswith("_NOISE") for n in names)


def test_round_trip_with_skymap_geometry(tmp_path):
    from cellcoadd.geometry.skymap import SkyMap

    tract = SkyMap.from_centers([(359.99, -89.5)], SMALL)[0]
    geometry = tract.patch(0, 0)
    meta = make_metadata(patch=(0, 0)).model_copy(
        update={"tract": tract.id, "tract_center": tract.center}
    )
    rng = np.random.default_rng(5)
    cells = {}
    for cell in geometry.cells:
        shape = cell.outer_bbox.shape
        cells[cell.index] = CellCoadd(
            image=random_float_bits(rng, shape),
            mask=np.zeros(shape, np.int32),
            variance=np.ones(shape, np.float32),
            noise=np.zeros((meta.n_noise, *shape), np.float32),
            mfrac=np.zeros(shape, np.float32),
            psf=np.full((5, 5), 1 / 25),
            inputs=make_records(rng, meta.band, 1, 1),
            tract=cell.tract,
            index=cell.index,
            inner_bbox=cell.inner_bbox,
            outer_bbox=cell.outer_bbox,
            wcs=cell.wcs,
        )
    original = PatchCoadd(meta, cells)
    assert (-1, -1) in original
    pixels = rng.uniform(-1, 14, size=(20, 2))
    for name in ("geo.fits", "geo.h5"):
        api.write(original, tmp_path / name)
        back = api.read(tmp_path / name)
        assert_same(back, original)
        for index, cell in original.items():
            np.testing.assert_array_equal(
                back[index].wcs.all_pix2world(pixels, 0), cell.wcs.all_pix2world(pixels, 0)
            )


def test_compression_is_lossless_and_smaller_for_smooth_data(tmp_path):
    # cells of 150 x 150 px: on 60 x 60 px cells the gain on Gaussian noise (~15%) is less
    # than a header block, and every plane HDU carries its WCS cards
    config = SkyMapConfig(cell_inner=100, cell_border=25, cells_per_patch=2, patches_per_tract=2)
    smooth = make_patch(config, seed=2, arbitrary_bits=False)
    sizes = {}
    for name in ("plain.fits", "packed.fits.fz", "plain.h5", "packed.h5"):
        compression = "lossless" if name.startswith("packed") else None
        api.write(smooth, tmp_path / name, compression=compression)
        assert_same(api.read(tmp_path / name), smooth)
        sizes[name] = (tmp_path / name).stat().st_size
    # Gaussian float32 noise compresses only modestly without quantisation.
    assert sizes["packed.fits.fz"] < sizes["plain.fits"]
    assert sizes["packed.h5"] < sizes["plain.h5"]


def test_write_api_errors(tmp_path, patch):
    with pytest.raises(ValueError, match=r"\.fits\.fz, \.fits, \.hdf5, \.h5"):
        api.write(patch, tmp_path / "patch.txt")
    with pytest.raises(ValueError, match="never quantised"):
        api.write(patch, tmp_path / "patch.fits", compression="rice")
    with pytest.raises(ValueError, match="tile compressed"):
        api.write(patch, tmp_path / "patch.fits.fz", compression="none")
    with pytest.raises(TypeError):
        api.write({"not": "a patch"}, tmp_path / "patch.fits")
    for name in ("patch(1,2).fits", "patch[1].fits"):  # CFITSIO would write another file
        with pytest.raises(ValueError, match="extended file-name syntax"):
            api.write(patch, tmp_path / name)
    assert os.listdir(tmp_path) == []
    with pytest.raises(FileNotFoundError):
        api.read(tmp_path / "absent.fits")
    api.write(patch, tmp_path / "patch.h5")
    with pytest.raises(FileExistsError, match="overwrite=True"):
        api.write(patch, tmp_path / "patch.h5")
    with pytest.raises(FileExistsError):
        api.convert(tmp_path / "patch.h5", tmp_path / "patch.h5")
    api.write(patch, tmp_path / "patch.h5", overwrite=True)
    with pytest.raises(KeyError, match="no cell"):
        api.read_cell(tmp_path / "patch.h5", (99, 99))
    assert sorted(os.listdir(tmp_path)) == ["patch.h5"]


def test_read_inputs_table(tmp_path, patch):
    api.write(patch, tmp_path / "patch.fits")
    with api.open(tmp_path / "patch.fits") as coadd_file:
        table = coadd_file.read_inputs()
    assert len(table) == sum(len(cell.inputs) for cell in patch.values())
    first = next(iter(patch))
    rows = table[(table["cell_x"] == first[0]) & (table["cell_y"] == first[1])]
    assert list(rows["visit"]) == [r.visit for r in patch[first].inputs]
    assert list(rows["status"]) == [r.status for r in patch[first].inputs]


# ----------------------------------------------------------------------------- corruption


def _flip(path: Path, offset: int, bit: int = 0) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 1 << bit
    path.write_bytes(bytes(data))


def _fits_offsets(path: Path, extname: str) -> dict[str, int]:
    with fitsio.FITS(str(path)) as fits:
        return fits[extname].get_offsets()


def _h5_chunk(path: Path, dataset: str) -> tuple[int, int]:
    with h5py.File(path, "r") as h5:
        info = h5[dataset].id.get_chunk_info(0)
        return info.byte_offset, info.size


@pytest.fixture(scope="module")
def written(tmp_path_factory, patch) -> dict[str, tuple[bytes, str]]:
    """Bytes of the module patch in each layout (compressed variants included)."""
    out = {}
    directory = tmp_path_factory.mktemp("written")
    for name, compression in (
        ("plain.fits", None),
        ("packed.fits.fz", None),
        ("plain.h5", None),
        ("packed.h5", "lossless"),
    ):
        api.write(patch, directory / name, compression=compression)
        out[name] = ((directory / name).read_bytes(), name)
    return out


def _outcome(path: Path, expected: PatchCoadd) -> str:
    """'error' for CellCoaddFormatError, 'equal' for an intact read; any other result fails."""
    try:
        result = api.read(path)
    except CellCoaddFormatError:
        return "error"
    assert result.equals(expected), "corrupted file read back as different data"
    return "equal"


@pytest.mark.parametrize("name", ["plain.fits", "packed.fits.fz", "plain.h5", "packed.h5"])
def test_truncation_at_random_offsets(tmp_path, written, patch, name):
    raw, _ = written[name]
    rng = np.random.default_rng(11)
    path = tmp_path / name
    for cut in [0, 1, 100, len(raw) - 1, *rng.integers(2, len(raw) - 1, size=25)]:
        path.write_bytes(raw[:cut])
        with pytest.raises(CellCoaddFormatError):
            api.read(path)


@pytest.mark.parametrize("name", ["plain.fits", "packed.fits.fz", "plain.h5", "packed.h5"])
def test_random_byte_flips_never_pass_silently(tmp_path, written, patch, name):
    raw, _ = written[name]
    rng = np.random.default_rng(12)
    path = tmp_path / name
    outcomes = []
    for _ in range(40):
        path.write_bytes(raw)
        _flip(path, int(rng.integers(0, len(raw))), int(rng.integers(0, 8)))
        outcomes.append(_outcome(path, patch))
    if name.endswith((".fits", ".fz")):
        # CHECKSUM covers every byte of a FITS file.
        assert set(outcomes) == {"error"}
    else:
        # Flips in unused HDF5 bytes are harmless; most bytes are checksummed.
        assert outcomes.count("error") >= 30


def test_fits_flips_in_header_metadata_and_pixels_are_caught(tmp_path, written, patch):
    raw, _ = written["packed.fits.fz"]
    path = tmp_path / "patch.fits.fz"
    cell = next(iter(patch))
    targets = {
        "primary header value": raw.index(b"TRACT   =") + 29,
        "metadata json": _metadata_offset(tmp_path, raw) + 20,
        "cell header": _offset_in(tmp_path, raw, fits_format.extname(cell, "mask"), "header") + 90,
        "pixel data": _offset_in(tmp_path, raw, fits_format.extname(cell, "image"), "data") + 7,
        "inputs table": _offset_in(tmp_path, raw, fits_format.extname(cell, "inputs"), "data") + 3,
    }
    for offset in targets.values():
        path.write_bytes(raw)
        _flip(path, offset)
        with pytest.raises(CellCoaddFormatError):
            api.read(path)


def _offset_in(tmp_path: Path, raw: bytes, extname: str, part: str) -> int:
    probe = tmp_path / "probe.fits"
    probe.write_bytes(raw)
    offsets = _fits_offsets(probe, extname)
    return offsets["header_start"] if part == "header" else offsets["data_start"]


def _metadata_offset(tmp_path: Path, raw: bytes) -> int:
    return _offset_in(tmp_path, raw, "METADATA", "data")


def test_hdf5_flips_in_pixel_chunks_are_caught_per_cell(tmp_path, written, patch):
    raw, _ = written["packed.h5"]
    path = tmp_path / "patch.h5"
    corrupted, intact = list(patch)[:2]
    for plane in ("image", "noise", "psf", "inputs"):
        path.write_bytes(raw)
        offset, size = _h5_chunk(path, f"cells/{hdf5_format.group_name(corrupted)}/{plane}")
        _flip(path, offset + size // 2, 3)
        with pytest.raises(CellCoaddFormatError, match="cell"):
            api.read_cell(path, corrupted)
        # Only the corrupted cell's bytes are involved in reading another cell.
        assert api.read_cell(path, intact).equals(patch[intact])
    path.write_bytes(raw)
    offset, size = _h5_chunk(path, "metadata")
    _flip(path, offset + 5)
    with pytest.raises(CellCoaddFormatError):
        api.read(path)


def test_fits_read_cell_touches_only_its_cell(tmp_path, written, patch):
    raw, _ = written["plain.fits"]
    path = tmp_path / "patch.fits"
    corrupted, intact = list(patch)[:2]
    path.write_bytes(raw)
    _flip(path, _offset_in(tmp_path, raw, fits_format.extname(corrupted, "variance"), "data") + 1)
    assert api.read_cell(path, intact).equals(patch[intact])
    with pytest.raises(CellCoaddFormatError, match="checksum"):
        api.read_cell(path, corrupted)
    # Without verification the flipped bit goes through: verify is on by default for a reason.
    assert not api.read_cell(path, corrupted, verify=False).equals(patch[corrupted])


class _OpenedObjects:
    """Stands in for h5py's ``h5o`` module inside ``h5py._hl.group``: records the name of
    every object the high-level API opens (groups and datasets, hence their attributes and
    bytes)."""

    def __init__(self, module):
        self.module = module
        self.names = []

    def __getattr__(self, name):
        return getattr(self.module, name)

    def open(self, *args, **kwargs):
        oid = self.module.open(*args, **kwargs)
        self.names.append(h5py.h5i.get_name(oid).decode("ascii"))
        return oid


@pytest.mark.parametrize("name", ["plain.h5", "packed.h5"])
def test_hdf5_read_cell_touches_only_its_cell(tmp_path, written, patch, monkeypatch, name):
    """Reading one cell opens the root's objects and that cell's group and datasets, and no
    object of any other cell (listing the names of /cells reads only its link index)."""
    path = tmp_path / "patch.h5"
    path.write_bytes(written[name][0])
    opened = _OpenedObjects(h5py._hl.group.h5o)
    monkeypatch.setattr(h5py._hl.group, "h5o", opened)
    for index in list(patch)[:3]:
        opened.names.clear()
        assert api.read_cell(path, index).equals(patch[index])
        group = f"/cells/{hdf5_format.group_name(index)}"
        outside = {n for n in opened.names if n not in ("/", "/cells", "/metadata")}
        outside = {n for n in outside if n != group and not n.startswith(group + "/")}
        assert not outside, f"reading cell {index} opened {sorted(outside)}"
        planes = {n.rsplit("/", 1)[1] for n in opened.names if n.startswith(group + "/")}
        held = {*patch[index].plane_names, cell_planes.INPUTS}
        assert planes == held  # the instrument sees the reads
    # a whole read opens every cell: the instrument would see another cell's objects
    opened.names.clear()
    api.read(path)
    assert {n.split("/")[2] for n in opened.names if n.count("/") >= 2} == {
        hdf5_format.group_name(index) for index in patch
    }


def test_missing_hdu_or_dataset(tmp_path, written, patch):
    raw, _ = written["plain.fits"]
    cell = next(iter(patch))
    for extname in (fits_format.extname(cell, "psf"), "METADATA", "CELLINDEX"):
        probe = tmp_path / "probe.fits"
        probe.write_bytes(raw)
        offsets = _fits_offsets(probe, extname)
        path = tmp_path / "cut.fits"
        path.write_bytes(raw[: offsets["header_start"]] + raw[offsets["data_end"] :])
        with pytest.raises(CellCoaddFormatError):
            api.read(path)
    for dataset in (f"cells/{hdf5_format.group_name(cell)}/mask", "metadata", "cells"):
        path = tmp_path / "cut.h5"
        path.write_bytes(written["plain.h5"][0])
        with h5py.File(path, "r+") as h5:
            del h5[dataset]
        with pytest.raises(CellCoaddFormatError):
            api.read(path)


@pytest.mark.parametrize("name", ["v.fits", "v.h5"])
def test_format_versions(tmp_path, monkeypatch, patch, name):
    def payload_with(version: str, extra: bool):
        def payload(metadata):
            data = json.loads(metadata.model_dump_json())
            data["format_version"] = version
            if extra:
                data["added_in_a_later_minor"] = [1, 2]
                data["build_config"]["new_knob"] = 0.5
            return json.dumps(data).encode("utf-8"), version

        return payload

    monkeypatch.setattr(format_version, "metadata_payload", payload_with("1.7", extra=True))
    api.write(patch, tmp_path / name)
    newer_minor = api.read(tmp_path / name)
    assert newer_minor.metadata.format_version == "1.7"
    assert (
        newer_minor.metadata.model_copy(update={"format_version": FORMAT_VERSION}) == patch.metadata
    )
    for version, extra, message in (("2.0", False, "major version 2"), ("1.0", True, "(?i)extra")):
        monkeypatch.setattr(format_version, "metadata_payload", payload_with(version, extra))
        api.write(patch, tmp_path / name, overwrite=True)
        with pytest.raises(CellCoaddFormatError, match=message):
            api.read(tmp_path / name)


def test_foreign_files_are_refused(tmp_path):
    cases = {
        "text.fits": b"hello, this is not a FITS file\n" * 10,
        "text.h5": b"hello, this is not an HDF5 file\n" * 10,
        "empty.fits": b"",
        "empty.h5": b"",
    }
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
    with fitsio.FITS(str(tmp_path / "exposure.fits"), "rw") as fits:
        fits.write(np.zeros((20, 30), dtype=np.float32), header={"EXPTIME": 30.0})
    with h5py.File(tmp_path / "exposure.h5", "w") as h5:
        h5["image"] = np.zeros((4, 4))
    (tmp_path / "hdf5-named.fits").write_bytes((tmp_path / "exposure.h5").read_bytes())
    (tmp_path / "fits-named.h5").write_bytes((tmp_path / "exposure.fits").read_bytes())
    for path in sorted(tmp_path.iterdir()):
        with pytest.raises(CellCoaddFormatError) as caught:
            api.read(path)
        assert caught.value.path == str(path)


# ---------------------------------------------------------------------------- atomic writes


@pytest.mark.parametrize("name", ["patch.fits", "patch.h5"])
def test_exception_mid_write_leaves_previous_file(tmp_path, monkeypatch, patch, name):
    path = tmp_path / name
    api.write(patch, path)
    before = path.read_bytes()
    module = fits_format if name.endswith(".fits") else hdf5_format
    original = module._write_cell
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) >= 3:
            raise RuntimeError("disk on fire")
        return original(*args, **kwargs)

    monkeypatch.setattr(module, "_write_cell", failing)
    with pytest.raises(RuntimeError, match="disk on fire"):
        api.write(make_patch(seed=9), path, overwrite=True)
    with pytest.raises(RuntimeError):
        api.write(patch, tmp_path / ("new-" + name))
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == [name]


_KILL_SCRIPT = """
import sys
sys.path.insert(0, {tests!r})
from coadd_factory import make_patch
from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.io import api
config = SkyMapConfig(cell_inner=150, cell_border=25, cells_per_patch=4, patches_per_tract=3)
big = make_patch(config, seed=3, n_noise=3, arbitrary_bits=False)
print("writing", flush=True)
api.write(big, {target!r}, compression="lossless", overwrite=True)
print("done", flush=True)
"""


@pytest.mark.parametrize("name", ["big.fits", "big.h5"])
@pytest.mark.parametrize("previous", [True, False])
def test_sigkill_mid_write_leaves_previous_file(tmp_path, patch, name, previous):
    target = tmp_path / name
    if previous:
        api.write(patch, target)
    before = target.read_bytes() if previous else None
    kill_mid_write(_KILL_SCRIPT, target)
    if previous:
        assert target.read_bytes() == before
        assert_same(api.read(target), patch)
    else:
        assert not target.exists()


# -------------------------------------------------------------------------------------- CLI


def test_cli_info_convert_schemas(tmp_path, patch):
    path = tmp_path / "patch.fits"
    api.write(patch, path)
    runner = CliRunner()
    result = runner.invoke(info_command, [str(path)])
    assert result.exit_code == 0, result.output
    assert "tract 7, patch (1, 1), band r" in result.output
    assert "16 (4 inner + 12 border), 1 empty" in result.output
    summary = json.loads(runner.invoke(info_command, [str(path), "--json"]).output)
    assert summary["cells"]["empty"] == 1
    assert summary["n_noise"] == 2 and summary["psf_size"] == 5
    assert summary["inputs"]["total"] == sum(len(c.inputs) for c in patch.values())
    assert sum(e["used"] for e in summary["per_cell"]) == sum(c.n_used for c in patch.values())
    result = runner.invoke(convert_command, [str(path), str(tmp_path / "patch.h5")])
    assert result.exit_code == 0, result.output
    assert_same(api.read(tmp_path / "patch.h5"), patch)
    again = runner.invoke(convert_command, [str(path), str(tmp_path / "patch.h5")])
    assert again.exit_code == 1 and "--overwrite" in again.output
    (tmp_path / "junk.fits").write_text("junk")
    bad = runner.invoke(info_command, [str(tmp_path / "junk.fits")])
    assert bad.exit_code == 1
    assert bad.output.startswith("Error: ") and bad.output.count("\n") == 1
    result = runner.invoke(schemas_command, ["--out", str(tmp_path / "schemas")])
    assert result.exit_code == 0 and (tmp_path / "schemas" / "PatchMetadata.v1.json").exists()
