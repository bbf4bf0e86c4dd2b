"""Faults while writing: killed writers and full disks leave the previous file (or
nothing) behind, never a partial file (see docs/reliability.md)."""

from __future__ import annotations

import errno
import functools
import os
import shutil
import subprocess
import sys
import types
from pathlib import Path

import fitsio
import pytest
from coadd_factory import MEDIUM, SMALL, make_patch, tiny_exposures, tiny_patch
from exposure_factory import make_exposure
from kill_writer import kill_mid_write

from cellcoadd import Exposure
from cellcoadd.io import api
from cellcoadd.io._fits import direct as fits_direct
from cellcoadd.io.coadd import hdf5_chunks
from cellcoadd.io.exposures import exposure_io
from cellcoadd.io.exposures.exposure_io import read_exposure, write_exposure

TESTS = Path(__file__).parent


@pytest.fixture(scope="module")
def exposure() -> Exposure:
    """A good exposure of the tiny patch."""
    return tiny_exposures(tiny_patch(), 1)[0]


# --------------------------------------------------------------------- killed writers

_KILL_EXPOSURE = """
import sys
sys.path.insert(0, {tests!r})
import galsim, numpy as np
from exposure_factory import make_wcs
from cellcoadd import Exposure, write_exposure
shape = (3000, 3000)
exposure = Exposure(
    image=np.ones(shape, np.float32), wcs=make_wcs((30.0, -10.0), shape, 0.2),
    variance=np.ones(shape), psf=galsim.Gaussian(sigma=0.4), visit=1, detector=2, band="r",
    zero_point=30.0,
)
print("writing", flush=True)
write_exposure(exposure, {target!r}, overwrite=True)
print("done", flush=True)
"""

_KILL_COADD = """
import sys
sys.path.insert(0, {tests!r})
from coadd_factory import make_patch
from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.io import api
config = SkyMapConfig(cell_inner=150, cell_border=25, cells_per_patch=4, patches_per_tract=3)
big = make_patch(config, seed=3, n_noise=3, arbitrary_bits=False)
print("writing", flush=True)
api.write(big, {target!r}, overwrite=True)
print("done", flush=True)
"""


@pytest.mark.parametrize("previous", [True, False])
def test_killed_exposure_writer_leaves_the_previous_file(tmp_path, exposure, previous):
    target = tmp_path / "exposure.fits"
    if previous:
        write_exposure(exposure, target)
    before = target.read_bytes() if previous else None
    kill_mid_write(_KILL_EXPOSURE, target)
    if previous:
        assert target.read_bytes() == before
        assert read_exposure(target).key == exposure.key
    else:
        assert not target.exists()


def test_killed_compressed_coadd_writer_leaves_the_previous_file(tmp_path):
    target = tmp_path / "patch.fits.fz"
    small = make_patch(SMALL, seed=4)
    api.write(small, target)
    before = target.read_bytes()
    kill_mid_write(_KILL_COADD, target)
    assert target.read_bytes() == before
    assert api.read(target).equals(small)


# ---------------------------------------------------------------------------- full disks

_BIG = make_patch(MEDIUM, seed=2)  # a few MB: more than the small disk holds


def _assert_disk_full(info: pytest.ExceptionInfo, target: Path) -> None:
    assert info.value.errno == errno.ENOSPC
    assert "disk full" in str(info.value) and info.value.filename == str(target)


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MiB tmpfs mounted for the test (needs root; skipped where mounting is refused)."""
    mount, umount = shutil.which("mount"), shutil.which("umount")
    if os.geteuid() != 0 or mount is None or umount is None:
        pytest.skip("mounting a small tmpfs needs root and mount(8)")
    point = tmp_path / "small-disk"
    point.mkdir()
    done = subprocess.run(
        [mount, "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(point)], capture_output=True
    )
    if done.returncode:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    try:
        yield point
    finally:
        if subprocess.run([umount, str(point)]).returncode:
            subprocess.run([umount, "-l", str(point)])


def _assert_exposure_too_big_for(directory: Path) -> None:
    big_exposure = make_exposure((30.0, -10.0), shape=(800, 800))  # 5 MB of float64
    with pytest.raises(OSError) as info:
        write_exposure(big_exposure, directory / "exposure.fits")
    _assert_disk_full(info, directory / "exposure.fits")


def test_full_disk_is_refused_before_writing(small_disk):
    small = make_patch(SMALL, seed=1)
    for name in ("patch.fits", "patch.h5"):
        target = small_disk / name
        api.write(small, target)
        before = target.read_bytes()
        with pytest.raises(OSError) as info:
            api.write(_BIG, target, overwrite=True)
        _assert_disk_full(info, target)
        assert target.read_bytes() == before
    _assert_exposure_too_big_for(small_disk)
    assert sorted(os.listdir(small_disk)) == ["patch.fits", "patch.h5"]


def test_disk_filling_up_during_a_fits_write(small_disk, monkeypatch):
    """Skip the up-front check so that CFITSIO itself runs out of space midway."""
    monkeypatch.setattr(api, "check_free_space", lambda *args: None)
    monkeypatch.setattr(exposure_io, "check_free_space", lambda *args: None)
    target = small_disk / "patch.fits"
    api.write(make_patch(SMALL, seed=1), target)
    before = target.read_bytes()
    with pytest.raises(OSError) as info:
        api.write(_BIG, target, overwrite=True)
    _assert_disk_full(info, target)
    assert target.read_bytes() == before
    _assert_exposure_too_big_for(small_disk)
    assert os.listdir(small_disk) == ["patch.fits"]


_HDF5_FILLS_DISK = """
import sys
sys.path.insert(0, {tests!r})
from coadd_factory import MEDIUM, make_patch
from cellcoadd.io import api
api.check_free_space = lambda *args: None
try:
    api.write(make_patch(MEDIUM, seed=2), {target!r}, overwrite=True)
except OSError as err:
    print(err.errno, err, flush=True)
"""


def test_disk_filling_up_during_an_hdf5_write_keeps_the_previous_file(small_disk):
    """Without the up-front check HDF5 2.0 runs into the full disk; it may then crash the
    process (a failed flush leaves its file half-open), but the previous file survives."""
    target = small_disk / "patch.h5"
    small = make_patch(SMALL, seed=1)
    api.write(small, target)
    before = target.read_bytes()
    code = _HDF5_FILLS_DISK.format(tests=str(TESTS), target=str(target))
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if done.returncode == 0:  # it survived: then the error was the clear one
        assert done.stdout.startswith(f"{errno.ENOSPC} ") and "disk full" in done.stdout
    assert target.read_bytes() == before
    assert api.read(target).equals(small)
    assert [p.name for p in small_disk.iterdir() if not p.name.startswith(".")] == [target.name]


@pytest.mark.parametrize("name", ["patch.fits", "patch.fits.fz", "patch.h5", "exposure.fits"])
def test_writer_running_out_of_space(tmp_path, monkeypatch, exposure, name):
    """The writing library reports ENOSPC midway (simulated): same clean outcome."""
    target = tmp_path / name
    if name.startswith("exposure"):
        write_exposure(exposure, target)
        owner, method = fitsio.FITS, "write"
    else:
        api.write(make_patch(SMALL, seed=1), target)
        # uncompressed cells are written directly, compressed ones through CFITSIO
        owner, method = (
            (hdf5_chunks.ObjectMaker, "dataset")
            if name.endswith("h5")
            else (fits_direct, "write_parts")
            if name.endswith(".fits")
            else (fitsio.FITS, "create_image_hdu")
        )
    before = target.read_bytes()
    original = getattr(owner, method)
    calls = []

    def fails_after_a_few(*args, **kwargs):
        calls.append(1)
        if len(calls) > 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, method, fails_after_a_few)
    with pytest.raises(OSError) as info:
        if name.startswith("exposure"):
            write_exposure(exposure, target, overwrite=True)
        else:
            api.write(make_patch(SMALL, seed=2), target, overwrite=True)
    _assert_disk_full(info, target)
    assert target.read_bytes() == before
    assert os.listdir(tmp_path) == [name]


def test_failures_on_a_nearly_full_disk_are_blamed_on_it(tmp_path, monkeypatch):
    """CFITSIO reports a full disk as an unrelated error: the free space decides."""
    free = {"bytes": 10**9}

    def statvfs(path):
        return types.SimpleNamespace(f_blocks=10**6, f_bavail=free["bytes"] // 4096, f_frsize=4096)

    def writer_filling_the_disk(patch, path, *, compress):
        Path(path).write_bytes(b"partial")
        free["bytes"] = 0
        raise OSError("FITSIO status = 252: 1st key not SIMPLE or XTENSION")

    monkeypatch.setattr(os, "statvfs", statvfs)
    monkeypatch.setitem(api._WRITERS, "fits", writer_filling_the_disk)
    target = tmp_path / "patch.fits"
    with pytest.raises(OSError) as info:
        api.write(make_patch(SMALL, seed=1), target)
    _assert_disk_full(info, target)
    assert os.listdir(tmp_path) == []
    # the same failure with space to spare is passed on as it is
    monkeypatch.setitem(api._WRITERS, "fits", functools.partial(_fails_plainly))
    free["bytes"] = 10**9
    with pytest.raises(OSError, match="status = 252") as info:
        api.write(make_patch(SMALL, seed=1), target)
    assert info.value.errno is None
    # and a write that cannot fit is refused before anything is written
    free["bytes"] = 1000
    monkeypatch.setitem(api._WRITERS, "fits", _never_called)
    with pytest.raises(OSError, match="disk full: writing needs up to"):
        api.write(make_patch(SMALL, seed=1), target)
    assert os.listdir(tmp_path) == []


def _fails_plainly(patch, path, *, compress):
    raise OSError("FITSIO status = 252: 1st key not SIMPLE or XTENSION")


def _never_called(*args, **kwargs):
    raise AssertionError("the writer ran although the disk is too full")
