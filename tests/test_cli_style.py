"""The command line speaks one error style, range-checks coordinates, prints configuration
values as a person would write them, and survey readers load DECam files without warnings.
"""

from __future__ import annotations

import warnings

import pytest
from conftest import DES_PSF
from test_presets import write_small_des

from cellcoadd.cli.main import main
from cellcoadd.io import DES_LAYOUT, MefExposureFile


def _run(capsys, *args: str) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as info:
        main(list(args))
        raise SystemExit(0)
    out = capsys.readouterr()
    return int(info.value.code or 0), out.out, out.err


@pytest.mark.parametrize(
    ("ra", "dec", "bad"),
    [("400", "-30", "RA"), ("-10", "5", "RA"), ("nan", "5", "RA"), ("10", "-95", "DEC")],
)
def test_locate_refuses_positions_off_the_sky(capsys, ra, dec, bad):
    code, out, err = _run(capsys, "locate", ra, dec)
    assert code == 2 and out == ""
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"error: Invalid value for {bad}:"), err
    assert ("[0, 360]" if bad == "RA" else "[-90, 90]") in last


def test_locate_accepts_the_edges_of_the_ranges(capsys):
    for ra, dec in (("0", "-90"), ("360", "90"), ("359.99", "-30")):
        code, out, err = _run(capsys, "locate", ra, dec, "--json")
        assert code == 0 and '"tract"' in out, err


@pytest.mark.parametrize(
    "args",
    [
        ("locate", "10", "-95"),  # a usage error (click)
        ("nocommand",),  # an unknown command (click)
        ("info", "/nonexistent/patch.fits"),  # a file error (click.Path)
        ("config",),  # a UsageError raised by the command
    ],
)
def test_every_error_is_one_lowercase_error_line(capsys, args):
    code, _, err = _run(capsys, *args)
    assert code != 0
    assert "Error:" not in err, err
    assert [line for line in err.splitlines() if "error" in line.lower()] == [
        err.strip().splitlines()[-1]
    ]
    assert err.strip().splitlines()[-1].startswith("error: ")


def test_library_errors_use_the_same_style(capsys, tmp_path):
    junk = tmp_path / "junk.fits"
    junk.write_text("not fits")
    code, _, err = _run(capsys, "info", str(junk))
    assert code == 1 and err.startswith(f"error: {junk}") and err.count("\n") == 1


def test_config_show_prints_the_values_a_person_writes(capsys):
    code, out, _ = _run(capsys, "config", "--show")
    assert code == 0
    assert "31.40006562228223" not in out
    assert "mapping_tolerance = 0.001" in out and "n_noise = 3" in out


def test_decam_files_load_without_warnings(tmp_path):
    """astropy's RADECSYS fix-up (and any other warning) stays inside the readers."""
    path = write_small_des(tmp_path / "D00154912_r_c12_r2369p01_immasked.fits.fz")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        source = MefExposureFile(path, DES_LAYOUT, DES_PSF)
        header = source.header()
        source.load()
        source.load_described(header)
