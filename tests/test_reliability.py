"""Hostile inputs and faults: bad exposures, full disks, killed writers, dying workers,
and byte-identical files whatever the executor (see docs/reliability.md)."""

from __future__ import annotations

import dataclasses
import errno
import functools
import hashlib
import multiprocessing
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import fitsio
import galsim
import h5py
import numpy as np
import pytest
from astropy.wcs import WCS
from coadd_factory import (
    MEDIUM,
    SMALL,
    TINY_BUILD,
    DyingPsf,
    cell_sized_exposure,
    make_patch,
    tiny_exposures,
    tiny_patch,
    tiny_skymap,
)
from exposure_factory import make_exposure, make_wcs

import cellcoadd.build.patch as patch_module
import cellcoadd.build.select as select_module
from cellcoadd import Box, BuildConfig, CellBuildError, Exposure, ExposureError, build_patch
from cellcoadd.cli.main import main as cli_main
from cellcoadd.io import api, exposure_io
from cellcoadd.io.exposure_io import read_exposure, write_exposure

TESTS = Path(__file__).parent
_DATE = re.compile(rb"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d")


@pytest.fixture(scope="module")
def tiny():
    """The tiny patch, two good exposures and their serial build."""
    patch = tiny_patch()
    good = tiny_exposures(patch, 2)
    return patch, good, build_patch(patch, good, TINY_BUILD, seed=1, progress=False)


# --------------------------------------------------------------- exposures refused up front


def _kwargs() -> dict:
    shape = (30, 40)
    return dict(
        image=np.zeros(shape),
        wcs=make_wcs((30.0, -10.0), shape, 0.26),
        variance=1.0,
        psf=galsim.Gaussian(sigma=0.4),
        visit=5,
        detector=2,
        band="r",
        zero_point=30.0,
    )


def _wcs(**changes) -> WCS:
    wcs = make_wcs((30.0, -10.0), (30, 40), 0.26)
    for name, value in changes.items():
        setattr(wcs.wcs, name, value)
    return wcs


def _other_wcs(ctypes: list[str]) -> WCS:
    wcs = WCS(naxis=len(ctypes))
    wcs.wcs.ctype = ctypes
    wcs.wcs.crval = [30.0, -10.0, 1e9][: len(ctypes)]
    wcs.wcs.cdelt = [-7e-5, 7e-5, 1e6][: len(ctypes)]
    return wcs


_NAN_PIXEL = np.zeros((30, 40))
_NAN_PIXEL[4, 7] = np.nan
REFUSED = {
    "unmasked NaN pixel": dict(image=_NAN_PIXEL),
    "unmasked inf pixel": dict(image=np.where(_NAN_PIXEL != _NAN_PIXEL, -np.inf, 0.0)),
    "complex image": dict(image=np.zeros((30, 40), complex)),
    "mask with unknown bits": dict(mask=np.full((30, 40), 1 << 20, np.int32)),
    "mask bit beyond int32": dict(mask=np.full((30, 40), 1 << 40, np.int64)),
    "float mask": dict(mask=np.zeros((30, 40))),
    "linear WCS": dict(wcs=_other_wcs(["X", "Y"])),
    "galactic WCS": dict(wcs=_other_wcs(["GLON-TAN", "GLAT-TAN"])),
    "WCS with a spectral axis": dict(wcs=_other_wcs(["RA---TAN", "DEC--TAN", "FREQ"])),
    "singular WCS": dict(wcs=_wcs(cd=np.zeros((2, 2)))),
    "non-finite WCS": dict(wcs=_wcs(crval=[np.nan, -10.0])),
    "even image PSF": dict(psf=galsim.Image(np.ones((4, 4)))),
    "non-finite image PSF": dict(psf=galsim.Image(np.full((5, 5), np.nan))),
    "zero image PSF": dict(psf=galsim.Image(np.zeros((5, 5)))),
    "array as PSF": dict(psf=np.ones((5, 5))),
    "huge zero point": dict(zero_point=1e6),
    "tiny zero point": dict(zero_point=-1e6),
    "NaN zero point": dict(zero_point=float("nan")),
    "text zero point": dict(zero_point="30"),
    "fractional visit": dict(visit=1.5),
    "control character in band": dict(band="r\n"),
    "empty band": dict(band=""),
    "variance of another shape": dict(variance=np.ones((3, 3))),
    "text variance": dict(variance="high"),
    "valid box outside the image": dict(valid_box=Box(x_start=0, x_stop=50, y_start=0, y_stop=9)),
}


@pytest.mark.parametrize("case", REFUSED)
def test_malformed_exposures_are_refused_at_construction(case):
    with pytest.raises(ExposureError, match=r"exposure \(visit=\S+, detector=2\): "):
        Exposure(**{**_kwargs(), **REFUSED[case]})


# ------------------------------------------------------------ inputs rejected, cell by cell


def _raising(x: float, y: float) -> galsim.GSObject:
    raise RuntimeError("PSF model unavailable here")


def _returns_even_image(x: float, y: float) -> galsim.Image:
    return galsim.Image(np.ones((4, 4)))


def _returns_nan_flux(x: float, y: float) -> galsim.GSObject:
    return galsim.Gaussian(sigma=0.4).withFlux(float("nan"))


def _returns_zero_flux(x: float, y: float) -> galsim.GSObject:
    return galsim.Gaussian(sigma=0.4, flux=0.0)


def _returns_nan_image(x: float, y: float) -> galsim.GSObject:
    return galsim.InterpolatedImage(galsim.Image(np.full((9, 9), np.nan), scale=0.2))


def _returns_huge(x: float, y: float) -> galsim.GSObject:
    return galsim.Gaussian(sigma=1e5)


def _bad_inputs(good: Exposure) -> dict[int, tuple[str, Exposure]]:
    """Valid exposures over the whole patch that every cell must reject: visit -> (reason,
    exposure)."""
    shape = good.shape
    grid = np.zeros(shape, bool)
    grid[::4, ::4] = True
    intrp = good.mask_bits.value("INTRP")  # a bit the build does not treat as bad
    variants = {
        "bad_weight": [
            dict(variance=0.0),
            dict(variance=-1.0),
            dict(variance=np.where(grid, 0.0, 1.0)),
            dict(variance=np.where(grid, np.nan, 1.0)),
            dict(zero_point=99.0),  # noise scaled below float32 range
            dict(zero_point=-49.0),  # and above it
        ],
        "bad_pixels": [dict(image=np.where(grid, np.nan, good.image), mask=grid * intrp)],
        "bad_psf": [
            dict(psf=psf)
            for psf in (
                _raising,
                _returns_even_image,
                _returns_nan_flux,
                _returns_zero_flux,
                _returns_nan_image,
                _returns_huge,
            )
        ],
    }
    out = {}
    for reason, changes in variants.items():
        for change in changes:
            visit = 100 + len(out)
            out[visit] = (reason, dataclasses.replace(good, visit=visit, **change))
    return out


@pytest.mark.filterwarnings("ignore::galsim.GalSimFFTSizeWarning")
def test_bad_inputs_are_rejected_and_change_nothing(tiny):
    patch, good, reference = tiny
    bad = _bad_inputs(good[0])
    far = make_exposure((210.0, 10.0), visit=300)  # on the other side of the sky
    built = build_patch(
        patch, [*good, *(e for _, e in bad.values()), far], TINY_BUILD, seed=1, progress=False
    )
    for index, cell in built.items():
        statuses = {record.visit: record.status for record in cell.inputs}
        assert statuses == {0: "used", 1: "used", **{v: r for v, (r, _) in bad.items()}}, index
        expected = reference[index]
        assert [r for r in cell.inputs if r.visit < 2] == expected.inputs
        # rejected inputs contribute nothing: the cell is bit-identical to the clean build
        for plane in ("image", "noise", "variance", "mfrac", "mask", "psf"):
            np.testing.assert_array_equal(getattr(cell, plane), getattr(expected, plane))


def test_masked_non_finite_pixels_are_used_without_spreading(tiny):
    patch, good, _ = tiny
    holes = good[0].image.copy()
    mask = good[0].mask.copy()
    holes[50:53, 50:60] = [[np.nan], [np.inf], [-np.inf]]
    mask[50:53, 50:60] = good[0].mask_bits.value("BAD")
    variance = np.where(np.isfinite(holes), 1.0, np.nan)  # unknown where the pixels are
    exposure = dataclasses.replace(good[0], image=holes, mask=mask, variance=variance)
    built = build_patch(patch, [exposure, good[1]], TINY_BUILD, progress=False)
    for cell in built.values():
        assert [r.status for r in cell.inputs] == ["used", "used"]
        for plane in (cell.image, cell.noise, cell.variance, cell.mfrac):
            assert np.isfinite(plane).all()
    assert max(cell.mfrac.max() for cell in built.values()) > 0.0  # the holes are recorded


def test_a_cell_falling_off_the_exposure_projection_is_an_edge(tiny, monkeypatch):
    """A WCS whose inverse fails inside the cell (NaN positions) gives an ``edge`` rejection
    instead of stopping the build."""
    patch, good, reference = tiny
    broken = dataclasses.replace(good[0], visit=7)
    original = select_module.map_box

    def partly_unmappable(coadd_wcs, box, exposure_wcs, **options):
        mapping = original(coadd_wcs, box, exposure_wcs, **options)
        if exposure_wcs is not broken.wcs:
            return mapping
        x = mapping.x.copy()
        x[x.shape[0] // 2, x.shape[1] // 2] = np.nan
        return dataclasses.replace(mapping, x=x)

    monkeypatch.setattr(select_module, "map_box", partly_unmappable)
    built = build_patch(patch, [*good, broken], TINY_BUILD, seed=1, progress=False)
    for index, cell in built.items():
        assert [r.status for r in cell.inputs] == ["used", "used", "edge"]
        np.testing.assert_array_equal(cell.image, reference[index].image)


@pytest.mark.parametrize(
    "psf",
    [_raising, _returns_even_image, _returns_nan_flux, _returns_huge],
    ids=lambda f: f.__name__,
)
def test_exposure_whose_psf_cannot_be_stored_is_refused(tmp_path, tiny, psf):
    exposure = dataclasses.replace(tiny[1][0], psf=psf)
    with pytest.raises(ExposureError, match=r"visit=0, detector=0\): its PSF cannot be stored"):
        write_exposure(exposure, tmp_path / "exposure.fits")
    assert os.listdir(tmp_path) == []


def test_inputs_that_cannot_share_a_patch_are_refused(tiny):
    patch, good, _ = tiny
    with pytest.raises(ValueError, match=r"duplicate input \(visit, detector\) = \(1, 0\)"):
        build_patch(patch, [*good, dataclasses.replace(good[0], visit=1)], progress=False)
    with pytest.raises(ValueError, match="several bands"):
        build_patch(patch, [good[0], dataclasses.replace(good[1], band="g")], progress=False)
    spaced = [dataclasses.replace(e, band="r ") for e in good]
    with pytest.raises(ValueError, match="cannot be recorded"):
        build_patch(patch, spaced, progress=False)
    with pytest.raises(ValueError, match="at least one exposure"):
        build_patch(patch, [], progress=False)


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


def _kill_mid_write(script: str, target: Path) -> None:
    """Run ``script`` (which writes ``target``) and SIGKILL it once its temporary file
    holds more than 2 MB."""
    code = script.format(tests=str(TESTS), target=str(target))
    process = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    partial = None
    try:
        if process.stdout.readline().strip() != "writing":
            process.wait(timeout=60)
            pytest.fail(f"the writer did not start: {process.stderr.read()[-2000:]}")
        deadline = time.monotonic() + 60
        while partial is None and time.monotonic() < deadline and process.poll() is None:
            for temporary in target.parent.glob(f".{target.name}.tmp-*"):
                if temporary.exists() and temporary.stat().st_size > 2_000_000:
                    partial = temporary
            time.sleep(0.002)
        process.send_signal(signal.SIGKILL)
    finally:
        process.kill()
        process.wait()
    assert partial is not None, "the writer finished before it could be interrupted"


@pytest.mark.parametrize("previous", [True, False])
def test_killed_exposure_writer_leaves_the_previous_file(tmp_path, tiny, previous):
    target = tmp_path / "exposure.fits"
    if previous:
        write_exposure(tiny[1][0], target)
    before = target.read_bytes() if previous else None
    _kill_mid_write(_KILL_EXPOSURE, target)
    if previous:
        assert target.read_bytes() == before
        assert read_exposure(target).key == tiny[1][0].key
    else:
        assert not target.exists()


def test_killed_compressed_coadd_writer_leaves_the_previous_file(tmp_path):
    target = tmp_path / "patch.fits.fz"
    small = make_patch(SMALL, seed=4)
    api.write(small, target)
    before = target.read_bytes()
    _kill_mid_write(_KILL_COADD, target)
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
    big_exposure = make_exposure((30.0, -10.0), shape=(800, 800))  # 5 MB of float64
    with pytest.raises(OSError) as info:
        write_exposure(big_exposure, small_disk / "exposure.fits")
    _assert_disk_full(info, small_disk / "exposure.fits")
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
    big_exposure = make_exposure((30.0, -10.0), shape=(800, 800))  # 5 MB of float64
    with pytest.raises(OSError) as info:
        write_exposure(big_exposure, small_disk / "exposure.fits")
    _assert_disk_full(info, small_disk / "exposure.fits")
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
def test_writer_running_out_of_space(tmp_path, monkeypatch, tiny, name):
    """The writing library reports ENOSPC midway (simulated): same clean outcome."""
    target = tmp_path / name
    exposure = tiny[1][0]
    if name.startswith("exposure"):
        write_exposure(exposure, target)
        owner, method = fitsio.FITS, "write"
    else:
        api.write(make_patch(SMALL, seed=1), target)
        owner, method = (
            (h5py.Group, "create_dataset")
            if name.endswith("h5")
            else (
                fitsio.FITS,
                "create_image_hdu",
            )
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


# ------------------------------------------------------------------------ dying workers


def _killer(patch) -> Exposure:
    """An exposure used by cell (0, 0) only, whose PSF kills any worker process drawing it."""
    return cell_sized_exposure(patch.tract.cell(0, 0), 50, DyingPsf(os.getpid()))


def _named_cell(message: str) -> tuple[int, int]:
    found = re.match(r"cell \((-?\d+), (-?\d+)\) of tract 0 failed", message)
    assert found, message
    return int(found.group(1)), int(found.group(2))


def test_a_worker_process_dying_is_reported_with_its_cell(tiny):
    patch, good, _ = tiny
    with pytest.raises(CellBuildError, match="a worker process died") as info:
        build_patch(patch, [*good, _killer(patch)], TINY_BUILD, progress=False, workers=2)
    message = str(info.value)
    assert _named_cell(message) in patch.cell_indices
    # the pool fails every unfinished cell at once; the culprit is among those named
    assert "(0, 0)" in message.split("BrokenProcessPool")[0]


def test_a_worker_raising_is_reported_with_its_cell(tiny):
    patch, good, _ = tiny
    config = BuildConfig(n_noise=1, psf_size=35)  # larger than the 32-pixel cells
    with pytest.raises(CellBuildError, match="ValueError: psf_size 35 exceeds") as info:
        build_patch(patch, good, config, progress=False, workers=2)
    assert _named_cell(str(info.value)) in patch.cell_indices
    assert "Traceback" in str(info.value)  # the worker's traceback travels with it


@pytest.fixture(scope="module")
def exposure_files(tmp_path_factory, tiny):
    directory = tmp_path_factory.mktemp("exposures")
    skymap = directory / "skymap.json"
    skymap.write_text(tiny_skymap().to_json())
    files = [str(write_exposure(e, directory / f"visit{e.visit}.fits")) for e in tiny[1]]
    return files, str(skymap)


def _cli_build(files: list[str], skymap: str, out: Path, *options: str) -> int:
    args = ["build", *files, "--skymap", skymap, "--tract", "0", "--patch", "0,0"]
    args += ["--out", str(out), "--n-noise", "1", "--quiet", *options]
    try:
        cli_main(args)
    except SystemExit as exit_:
        return int(exit_.code or 0)
    return 0


def test_cli_build_failing_in_a_worker_writes_nothing(tmp_path, exposure_files, capsys):
    files, skymap = exposure_files
    out = tmp_path / "patch.fits"
    code = _cli_build(files, skymap, out, "--workers", "2", "--psf-size", "35")
    error = capsys.readouterr().err
    assert code == 1 and error.startswith("error: cell (") and error.count("\n") == 1
    assert os.listdir(tmp_path) == []
    assert _cli_build(files, skymap, out, "--workers", "2", "--psf-size", "11") == 0
    assert api.read(out).metadata.build_config.psf_size == 11


def _die_in_workers(parent_pid: int, *args, **kwargs):
    if os.getpid() != parent_pid:
        os._exit(9)
    raise RuntimeError("build_cell replaced by a test ran in the parent process")


@pytest.mark.skipif(
    multiprocessing.get_start_method() != "fork",
    reason="the replaced build_cell reaches worker processes only when they are forked",
)
def test_cli_build_with_a_dying_worker_writes_nothing(
    tmp_path, exposure_files, capsys, monkeypatch
):
    files, skymap = exposure_files
    monkeypatch.setattr(patch_module, "build_cell", functools.partial(_die_in_workers, os.getpid()))
    out = tmp_path / "patch.h5"
    code = _cli_build(files, skymap, out, "--workers", "2", "--psf-size", "11")
    error = capsys.readouterr().err
    assert code == 1 and "a worker process died" in error and error.startswith("error: cell (")
    assert os.listdir(tmp_path) == []


# ------------------------------------------------- reproducibility, and dask (tests last)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_written_files_carry_no_timestamps(tmp_path, tiny):
    _, good, serial = tiny
    for name in ("a.fits", "a.fits.fz", "a.h5"):
        api.write(serial, tmp_path / name)
        assert _DATE.search((tmp_path / name).read_bytes()) is None, name
    write_exposure(good[0], tmp_path / "e1.fits")
    write_exposure(good[0], tmp_path / "e2.fits")
    assert _DATE.search((tmp_path / "e1.fits").read_bytes()) is None
    assert _sha256(tmp_path / "e1.fits") == _sha256(tmp_path / "e2.fits")
    with fitsio.FITS(str(tmp_path / "a.fits")) as fits:
        for hdu in fits:
            hdu.verify_checksum()  # the rewritten checksum cards are valid FITS checksums


@pytest.fixture(scope="module")
def dask_client():
    distributed = pytest.importorskip("distributed")
    import dask

    # one death is enough to fail a task (KilledWorker) instead of retrying it elsewhere
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        cluster = distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        )
        client = distributed.Client(cluster)
    yield client
    client.close()
    cluster.close()


def test_files_are_byte_identical_whatever_the_executor(tmp_path, tiny, dask_client):
    patch, good, serial = tiny
    builds = {
        "serial": serial,
        "pool": build_patch(patch, good, TINY_BUILD, seed=1, progress=False, workers=2),
        "dask": build_patch(patch, good, TINY_BUILD, seed=1, progress=False, scheduler=dask_client),
    }
    for name in ("patch.fits", "patch.fits.fz", "patch.h5"):
        digests = {}
        for executor, coadd in builds.items():
            api.write(coadd, tmp_path / f"{executor}-{name}")
            digests[executor] = _sha256(tmp_path / f"{executor}-{name}")
        assert len(set(digests.values())) == 1, (name, digests)


def test_a_raising_cell_on_dask_is_named(tiny, dask_client):
    patch, good, _ = tiny
    config = BuildConfig(n_noise=1, psf_size=35)
    with pytest.raises(CellBuildError, match="ValueError: psf_size 35 exceeds") as info:
        build_patch(patch, good, config, progress=False, scheduler=dask_client)
    assert _named_cell(str(info.value)) in patch.cell_indices


@pytest.mark.slow  # timing-dependent on a loaded 2-core machine: passes about half the time
def test_a_dying_dask_worker_is_named_exactly(tiny, dask_client):
    patch, good, _ = tiny
    with pytest.raises(CellBuildError, match="KilledWorker") as info:
        build_patch(
            patch, [*good, _killer(patch)], TINY_BUILD, progress=False, scheduler=dask_client
        )
    assert _named_cell(str(info.value)) == (0, 0)
