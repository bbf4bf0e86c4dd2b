"""Contracts every user relies on: one error hierarchy, typed selection results, statuses
as an enum, frozen exposures, bands enforced, and a cheap ``import cellcoadd``."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
from exposure_factory import make_exposure

import cellcoadd
from cellcoadd import BuildConfig, InputStatus, SkyMap, SkyMapConfig, build_cell
from cellcoadd import errors as errors_module
from cellcoadd.builder import select as select_module
from cellcoadd.builder.select import Candidate, Rejection, select_exposure

CONFIG = SkyMapConfig(
    pixel_scale=0.2, cell_inner=40, cell_border=10, cells_per_patch=2, patches_per_tract=2
)
BUILD = BuildConfig(n_noise=1, psf_size=15)


@pytest.fixture(scope="module")
def cell():
    return SkyMap.from_centers([(30.0, -10.0)], CONFIG)[0].cell(0, 0)


def test_every_error_is_a_cellcoadd_error():
    classes = [
        value
        for value in vars(errors_module).values()
        if isinstance(value, type)
        and issubclass(value, Exception)
        and not issubclass(value, Warning)
    ]
    assert len(classes) >= 10
    assert all(issubclass(cls, cellcoadd.CellCoaddError) for cls in classes)
    # warnings are warnings, which a filter can silence
    assert issubclass(errors_module.PsfStampWarning, UserWarning)
    # the public names are the same objects as their homes'
    assert cellcoadd.ExposureError is errors_module.ExposureError
    assert cellcoadd.CellBuildError is errors_module.CellBuildError


def test_statuses_are_an_enum_stored_as_strings(cell):
    assert [s.value for s in InputStatus][0] == "used"
    assert InputStatus.EDGE == "edge" and f"{InputStatus.EDGE}" == "edge"
    far = make_exposure((cell.center_sky[0] + 1.0, cell.center_sky[1]), visit=2)
    coadd = build_cell(cell, [make_exposure(cell.center_sky, visit=1), far], BUILD)
    record = {r.visit: r for r in coadd.inputs}[2]
    assert record.status == InputStatus.NO_OVERLAP
    assert json.loads(record.model_dump_json())["status"] == "no_overlap"


def test_selection_returns_typed_results(cell):
    used = select_exposure(cell, make_exposure(cell.center_sky), BUILD, bad_bits=0)
    assert isinstance(used, Candidate) and used.weight > 0
    small = make_exposure(cell.center_sky, shape=(20, 20))
    edge = select_exposure(cell, small, BUILD, bad_bits=0)
    assert isinstance(edge, Rejection) and edge.status is InputStatus.EDGE
    assert 0.0 < edge.overlap_fraction < 1.0


def test_a_bug_in_selection_propagates(cell, monkeypatch):
    """Only what a WCS raises means "no overlap"; anything else is a bug and surfaces."""

    def broken(*args, **kwargs):
        raise TypeError("a bug, not a WCS failure")

    monkeypatch.setattr(select_module, "map_box", broken)
    with pytest.raises(TypeError, match="a bug"):
        select_exposure(cell, make_exposure(cell.center_sky), BUILD, bad_bits=0)


def test_exposures_of_another_band_are_rejected(cell):
    r_band = make_exposure(cell.center_sky, visit=1)
    i_band = dataclasses.replace(make_exposure(cell.center_sky, visit=2), band="i")
    coadd = build_cell(cell, [r_band, i_band], BUILD)
    assert {r.visit: r.status for r in coadd.inputs} == {1: "used", 2: "band_mismatch"}
    alone = build_cell(cell, [r_band], BUILD)
    np.testing.assert_array_equal(coadd.image, alone.image)
    coadd = build_cell(cell, [r_band, i_band], BUILD, band="i")
    assert {r.visit: r.status for r in coadd.inputs} == {1: "band_mismatch", 2: "used"}


def test_exposures_are_frozen():
    exposure = make_exposure((30.0, -10.0))
    with pytest.raises(dataclasses.FrozenInstanceError):
        exposure.zero_point = float("nan")  # type: ignore[misc]
    with pytest.raises(cellcoadd.ExposureError, match="zero_point"):
        dataclasses.replace(exposure, zero_point=float("nan"))


def test_import_is_cheap():
    """``import cellcoadd`` loads none of the heavy dependencies (measured in a fresh
    interpreter; the time is printed for the record, not asserted)."""
    code = (
        "import sys, time; t = time.perf_counter(); import cellcoadd; "
        "t = time.perf_counter() - t; "
        "heavy = [m for m in ('numba', 'matplotlib', 'dask', 'distributed', 'galsim', "
        "'astropy', 'h5py', 'fitsio', 'scipy') if m in sys.modules]; "
        "print(t, ','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    seconds, heavy = out.stdout.split()[0], out.stdout.split()[1:]
    assert heavy == [], f"import cellcoadd loaded {heavy} ({seconds} s)"


def test_lazy_exports_resolve():
    for name in cellcoadd.__all__:
        assert getattr(cellcoadd, name) is not None, name
    with pytest.raises(AttributeError):
        cellcoadd.no_such_name  # noqa: B018


def test_cli_help_lists_every_command_without_importing_them():
    from cellcoadd.cli.main import COMMANDS, cli

    code = (
        "import sys; from cellcoadd.cli import main; "
        "sys.argv = ['cellcoadd', '--help']\n"
        "try:\n    main()\nexcept SystemExit:\n    pass\n"
        "print('HEAVY', [m for m in ('numba', 'galsim', 'matplotlib', 'astropy', 'h5py') "
        "if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "HEAVY []" in out.stdout
    for name, (_, _, short) in COMMANDS.items():
        assert f"{name} " in out.stdout and short in out.stdout
        command = cli.get_command(None, name)  # type: ignore[arg-type]
        assert command is not None and command.name == name
        # the listed line says what the command's own help says first
        assert short.split()[0] == command.get_short_help_str(200).split()[0], name
