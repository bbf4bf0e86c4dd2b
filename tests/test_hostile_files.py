"""Hostile files and bad inputs: no silent wrong result, memory bounded by what a file
really holds (see the table in docs/reliability.md).

HDF5 structure (links, external storage, deleted cells), declared sizes, CFITSIO file-name
syntax, mask-bit names, stale temporary files, non-finite builds and CLI checks up front.
"""

from __future__ import annotations

import dataclasses
import gzip
import json
import os
import subprocess
import sys

import fitsio
import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from coadd_factory import TINY_BUILD, assert_same, make_patch, tiny_exposures, tiny_patch

from cellcoadd import build_patch
from cellcoadd.cli.build import build as build_command
from cellcoadd.cli.demo import demo as demo_command
from cellcoadd.cli.storage import info_command
from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.io import api
from cellcoadd.io._files import atomic
from cellcoadd.io.coadd import format_version
from cellcoadd.io.coadd.format_version import sha256_hex
from cellcoadd.io.exposures.exposure_io import read_exposure, write_exposure
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.patch_coadd import PatchCoadd


@pytest.fixture(scope="module")
def patch():
    return make_patch(seed=3)


@pytest.fixture(scope="module")
def h5_bytes(patch, tmp_path_factory) -> bytes:
    path = tmp_path_factory.mktemp("h5") / "patch.h5"
    api.write(patch, path)
    return path.read_bytes()


def _edited(tmp_path, h5_bytes, edit, name="edited.h5"):
    path = tmp_path / name
    path.write_bytes(h5_bytes)
    with h5py.File(path, "r+") as h5:
        edit(h5, tmp_path)
    return path


def _cells(h5):
    return sorted(h5["cells"])


# ------------------------------------------------------------------------ HDF5 structure


def _external_cell(h5, tmp_path):
    # the cell group comes from another (valid) file: same content, other object
    other = tmp_path / "other.h5"
    other.write_bytes(open(h5.filename, "rb").read())
    name = _cells(h5)[0]
    del h5["cells"][name]
    h5["cells"][name] = h5py.ExternalLink(str(other), f"/cells/{name}")


def _soft_plane(h5, tmp_path):
    first, second = _cells(h5)[:2]
    del h5[f"cells/{first}/mask"]
    h5[f"cells/{first}/mask"] = h5py.SoftLink(f"/cells/{second}/mask")


def _hard_plane(h5, tmp_path):
    first, second = _cells(h5)[:2]
    del h5[f"cells/{first}/inputs"]
    h5[f"cells/{first}/inputs"] = h5[f"cells/{second}/inputs"]


def _external_all_cells(h5, tmp_path):
    other = tmp_path / "other.h5"
    other.write_bytes(open(h5.filename, "rb").read())
    del h5["cells"]
    h5["cells"] = h5py.ExternalLink(str(other), "/cells")


def _hard_cell(h5, tmp_path):
    first, second = _cells(h5)[:2]
    del h5["cells"][first]
    h5["cells"][first] = h5["cells"][second]


def _external_storage(h5, tmp_path):
    name = _cells(h5)[0]
    data = h5[f"cells/{name}/image"][()]
    raw = tmp_path / "pixels.bin"
    raw.write_bytes(np.zeros_like(data).tobytes())
    del h5[f"cells/{name}/image"]
    dataset = h5[f"cells/{name}"].create_dataset(
        "image", shape=data.shape, dtype=data.dtype, external=[(str(raw), 0, data.nbytes)]
    )
    dataset.attrs["plane"] = np.bytes_("image")


def _virtual(h5, tmp_path):
    name = _cells(h5)[0]
    data = h5[f"cells/{name}/variance"]
    layout = h5py.VirtualLayout(shape=data.shape, dtype=data.dtype)
    layout[...] = h5py.VirtualSource(data)
    del h5[f"cells/{name}/image"]
    h5[f"cells/{name}"].create_virtual_dataset("image", layout)
    h5[f"cells/{name}/image"].attrs["plane"] = np.bytes_("image")


STRUCTURE_EDITS = {
    "external link to a cell": _external_cell,
    "soft link to another cell's plane": _soft_plane,
    "hard link to another cell's inputs": _hard_plane,
    "external link for /cells": _external_all_cells,
    "hard link to another cell": _hard_cell,
    "external storage": _external_storage,
    "virtual dataset": _virtual,
}


@pytest.mark.parametrize("verify", [True, False])
@pytest.mark.parametrize("edit", list(STRUCTURE_EDITS))
def test_hdf5_links_external_storage_and_virtual_datasets_are_refused(
    tmp_path, h5_bytes, edit, verify
):
    path = _edited(tmp_path, h5_bytes, STRUCTURE_EDITS[edit])
    with pytest.raises(CellCoaddFormatError):
        api.read(path, verify=verify)


def test_hdf5_deleted_cell_group_is_refused(tmp_path, h5_bytes):
    def delete(h5, _):
        del h5["cells"][_cells(h5)[3]]

    path = _edited(tmp_path, h5_bytes, delete)
    for verify in (True, False):
        with pytest.raises(CellCoaddFormatError, match="missing"):
            api.open(path, verify=verify)
    result = CliRunner().invoke(info_command, [str(path)])
    assert result.exit_code != 0
    assert "missing" in result.output


def test_hdf5_extra_cell_group_or_object_is_refused(tmp_path, h5_bytes):
    def copy_cell(h5, _):
        h5.copy(h5["cells"][_cells(h5)[0]], "cells/99_99")

    with pytest.raises(CellCoaddFormatError, match="not listed"):
        api.open(_edited(tmp_path, h5_bytes, copy_cell))

    def extra_plane(h5, _):
        h5["cells"][_cells(h5)[0]].create_dataset("extra", data=np.zeros(3))

    with pytest.raises(CellCoaddFormatError, match="unexpected"):
        api.read(_edited(tmp_path, h5_bytes, extra_plane))


def test_hdf5_files_written_before_the_cell_list_still_read(tmp_path, patch, monkeypatch):
    """Format 1.1 had no ``contents`` attribute: such files read as before."""
    real = format_version.metadata_payload

    def as_1_1(metadata):
        payload, _ = real(metadata)
        data = json.loads(payload)
        data["format_version"] = "1.1"
        return json.dumps(data).encode("utf-8"), "1.1"

    monkeypatch.setattr(format_version, "metadata_payload", as_1_1)
    path = tmp_path / "old.h5"
    api.write(patch, path)
    with h5py.File(path, "r+") as h5:
        del h5.attrs["contents"]
        del h5.attrs["contents_sha256"]
    monkeypatch.undo()
    read = api.read(path)
    assert read.metadata.format_version == "1.1"
    current = read.metadata.model_copy(update={"format_version": patch.metadata.format_version})
    assert_same(PatchCoadd(current, dict(read.cells)), patch)


# ------------------------------------------------------------------------ declared sizes


def test_hdf5_inputs_of_fill_value_rows_are_refused(tmp_path, h5_bytes):
    """A million declared rows that the file does not store: refused before allocating."""

    def million_rows(h5, _):
        group = h5["cells"][_cells(h5)[0]]
        dtype = group["inputs"].dtype
        del group["inputs"]
        dataset = group.create_dataset(
            "inputs", shape=(1_000_000,), dtype=dtype, chunks=(1_000_000,), fletcher32=True
        )
        dataset.attrs["plane"] = np.bytes_("inputs")

    path = _edited(tmp_path, h5_bytes, million_rows)
    assert path.stat().st_size < 200_000
    with pytest.raises(CellCoaddFormatError, match="declares"):
        api.read(path)
    result = CliRunner().invoke(info_command, [str(path)])
    assert result.exit_code != 0


@pytest.mark.parametrize("name", ["forged.h5", "forged.fits"])
def test_forged_psf_size_is_refused(tmp_path, patch, monkeypatch, name):
    """psf_size 4001 in cells of 14 pixels would read as gigabytes of fill values."""
    real = format_version.metadata_payload

    def forged(metadata):
        payload, version = real(metadata)
        data = json.loads(payload)
        data["build_config"]["psf_size"] = 4001
        return json.dumps(data).encode("utf-8"), version

    monkeypatch.setattr(format_version, "metadata_payload", forged)
    path = tmp_path / name
    api.write(patch, path)
    with pytest.raises(CellCoaddFormatError, match="psf_size 4001"):
        api.open(path)


def test_hdf5_cell_boxes_must_match_the_geometry(tmp_path, h5_bytes):
    """A cell identity with a forged (huge) outer box is refused, its sha recomputed."""

    def forge(h5, _):
        group = h5["cells"][_cells(h5)[0]]
        record = json.loads(bytes(group.attrs["cell"]))
        record["outer_bbox"]["x_stop"] += 100_000
        text = json.dumps(record).encode("ascii")
        group.attrs["cell"] = np.bytes_(text)
        group.attrs["cell_sha256"] = np.bytes_(sha256_hex(text))

    with pytest.raises(CellCoaddFormatError, match="outer box"):
        api.read(_edited(tmp_path, h5_bytes, forge))


@pytest.fixture()
def exposure():
    return tiny_exposures(tiny_patch(), 1)[0]


def test_gzip_stream_named_fits_is_refused_before_cfitsio(tmp_path, exposure, monkeypatch):
    path = tmp_path / "e.fits"
    write_exposure(exposure, path)
    path.write_bytes(gzip.compress(path.read_bytes()))

    real = fitsio.FITS

    def no_open(name, *args, **kwargs):
        if os.path.basename(str(name)) == "e.fits":
            raise AssertionError("CFITSIO opened a gzip stream")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(fitsio, "FITS", no_open)
    with pytest.raises(CellCoaddFormatError, match="not a FITS file"):
        read_exposure(path)


def test_exposure_mask_shape_is_checked_before_reading(tmp_path, exposure, monkeypatch):
    """A MASK header declaring 12000 x 12000 (e.g. tile-compressed) is refused from its
    header: no pixel of it is read."""
    path = tmp_path / "e.fits"
    write_exposure(exposure, path)
    dims, read = fitsio.hdu.ImageHDU.get_dims, fitsio.hdu.ImageHDU.read
    reads = []

    def get_dims(self):
        return [12000, 12000] if self.get_extname() == "MASK" else dims(self)

    def counted_read(self, *args, **kwargs):
        reads.append(self.get_extname())
        return read(self, *args, **kwargs)

    monkeypatch.setattr(fitsio.hdu.ImageHDU, "get_dims", get_dims)
    monkeypatch.setattr(fitsio.hdu.ImageHDU, "read", counted_read)
    with pytest.raises(CellCoaddFormatError, match="MASK"):
        read_exposure(path)
    assert "MASK" not in reads and "IMAGE" not in reads


# ------------------------------------------------------------------------ paths and names


@pytest.mark.parametrize("name", ["y.fits", "y.fits.fz"])
def test_cfitsio_overwrite_syntax_never_applies(tmp_path, monkeypatch, patch, name):
    """``!dir/y.fits`` is the file of that name, not CFITSIO's 'overwrite dir/y.fits'."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "!dir").mkdir()
    (tmp_path / "dir").mkdir()
    decoy = make_patch(seed=9)
    api.write(decoy, f"dir/{name}")
    api.write(patch, f"!dir/{name}")
    assert sorted(os.listdir(tmp_path / "dir")) == [name]  # no temporary file went there
    assert sorted(os.listdir(tmp_path / "!dir")) == [name]
    assert_same(api.read(f"!dir/{name}"), patch)
    assert_same(api.read(f"dir/{name}"), decoy)


def test_cfitsio_overwrite_syntax_never_applies_to_exposures(tmp_path, monkeypatch, exposure):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "!dir").mkdir()
    (tmp_path / "dir").mkdir()
    write_exposure(dataclasses.replace(exposure, visit=77), "dir/e.fits")
    write_exposure(exposure, "!dir/e.fits")
    assert sorted(os.listdir(tmp_path / "dir")) == ["e.fits"]
    assert read_exposure("!dir/e.fits").visit == exposure.visit
    assert read_exposure("dir/e.fits").visit == 77


@pytest.mark.parametrize(
    "bits",
    [{"É": 0}, {"BAD": 0, "naïve": 1}, {"BAD": 0, "bad": 1}, {"X" * 33: 0}],
)
def test_mask_bit_names_follow_fits_keyword_rules(bits):
    with pytest.raises(ValueError):
        MaskBits(bits=bits)


def test_longest_mask_bit_name_round_trips(tmp_path, exposure):
    name = "L" * 32
    bits = MaskBits(bits={**exposure.mask_bits.bits, name: 20})
    write_exposure(dataclasses.replace(exposure, mask_bits=bits), tmp_path / "e.fits")
    assert read_exposure(tmp_path / "e.fits").mask_bits == bits


def _dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


@pytest.mark.parametrize("name", ["p.fits", "p.h5"])
def test_stale_temporaries_of_killed_writers_are_removed(tmp_path, patch, name):
    target = tmp_path / name
    host = atomic._host_tag()
    stale = tmp_path / f".{name}.tmp-{host}-{_dead_pid()}-{'0' * 16}"
    live = tmp_path / f".{name}.tmp-{host}-{os.getppid()}-{'1' * 16}"
    other_target = tmp_path / f".q.fits.tmp-{host}-{_dead_pid()}-{'2' * 16}"
    other_host = tmp_path / f".{name}.tmp-elsewhere{host}-{_dead_pid()}-{'3' * 16}"
    for path in (stale, live, other_target, other_host):
        path.write_bytes(b"partial")
    api.write(patch, target)
    assert not stale.exists()
    assert live.exists() and other_target.exists() and other_host.exists()
    assert atomic.temporary_name(target).startswith(f".{name}.tmp-{host}-{os.getpid()}-")


# ------------------------------------------------------------------------ builder inputs


@pytest.fixture(scope="module")
def tiny():
    patch = tiny_patch()
    good = tiny_exposures(patch, 2)
    return patch, good, build_patch(patch, good, TINY_BUILD, seed=1, progress=False)


@pytest.mark.parametrize("plane", ["image", "variance"])
def test_a_huge_finite_pixel_is_rejected_and_changes_nothing(tiny, plane):
    patch, good, reference = tiny
    image = good[0].image.copy()
    variance = np.full(image.shape, good[0].background_variance)
    values = {"image": image, "variance": variance}
    values[plane][60, 60] = 1e300
    hostile = dataclasses.replace(good[0], visit=5, image=image, variance=variance)
    config = TINY_BUILD.model_copy(update={"noise_variance": "pixel"})
    built = build_patch(patch, [*good, hostile], config, seed=1, progress=False)
    clean = build_patch(patch, good, config, seed=1, progress=False)
    rejected = 0
    for index, cell in built.items():
        for name in ("image", "noise", "variance"):
            assert np.isfinite(getattr(cell, name)).all(), (index, name)
        if {r.visit: r.status for r in cell.inputs}.get(5) == "bad_pixels":
            rejected += 1  # the cells whose footprint holds the pixel: as without it
            for name in ("image", "noise", "variance", "mask", "psf"):
                np.testing.assert_array_equal(getattr(cell, name), getattr(clean[index], name))
    assert rejected > 0


def test_a_coadd_with_non_finite_pixels_is_never_returned(tiny, monkeypatch):
    """Should an overflow slip past selection, the cell fails by name."""
    import cellcoadd.builder.select as select_module
    from cellcoadd.errors import CellBuildError

    patch, good, _ = tiny
    monkeypatch.setattr(select_module, "_LARGEST_INPUT", float("inf"))
    image = good[0].image.copy()
    image[60, 60] = 1e300
    hostile = dataclasses.replace(good[0], image=image)
    with pytest.raises(CellBuildError, match="non-finite"):
        build_patch(patch, [hostile, good[1]], TINY_BUILD, seed=1, progress=False)


# ------------------------------------------------------------------------ the CLI, up front


@pytest.mark.parametrize("out", ["a[1]", "b(2)"])
def test_demo_refuses_a_bad_out_before_any_work(tmp_path, out, monkeypatch):
    import cellcoadd.pipelines.demo as demo_module

    def no_run(*args, **kwargs):
        raise AssertionError("the demo started")

    monkeypatch.setattr(demo_module, "run_demo", no_run)
    result = CliRunner().invoke(demo_command, ["--out", str(tmp_path / out), "--quiet"])
    assert result.exit_code != 0 and "AssertionError" not in repr(result.exception)
    assert "FITS paths" in result.output


def test_demo_asks_for_overwrite_on_an_existing_output(tmp_path, monkeypatch):
    import cellcoadd.pipelines.demo as demo_module

    calls = []
    monkeypatch.setattr(demo_module, "run_demo", lambda *a, **k: calls.append(a))
    (tmp_path / "coadd.fits").write_bytes(b"an earlier coadd")
    result = CliRunner().invoke(demo_command, ["--out", str(tmp_path), "--quiet"])
    assert result.exit_code != 0 and "--overwrite" in result.output
    assert not calls and (tmp_path / "coadd.fits").read_bytes() == b"an earlier coadd"


def test_build_refuses_a_bad_out_before_reading_inputs(tmp_path, exposure):
    write_exposure(exposure, tmp_path / "e.fits")
    for out, message in (
        (tmp_path / "missing" / "p.fits", "does not exist"),
        (tmp_path / "p.txt", "unsupported"),
        (tmp_path / "x[1].fits", "not allowed"),
    ):
        result = CliRunner().invoke(
            build_command,
            [str(tmp_path / "e.fits"), "--tract", "0", "--patch", "0,0", "--out", str(out)],
        )
        assert result.exit_code != 0 and message in result.output, result.output
