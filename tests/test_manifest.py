"""Manifests and build configurations for the command line, checked before any work."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from cellcoadd import BuildConfig
from cellcoadd.cli.main import cli
from cellcoadd.errors import CellCoaddFormatError, ConfigError
from cellcoadd.io.exposures.manifest_io import build_config_toml, read_build_config, read_manifest

TOML = """
[[exposures]]
path = "D00154912_r_c12_immasked.fits.fz"
layout = "des"
psf = "D00154912_r_c12_psfexcat.psf"
background = "D00154912_r_c12_bkg.fits.fz"

[[exposures]]
path = "calexp_R22_S11.fits"
layout = "lsst"
psf = "calexp_R22_S11.piff"
zero_point = 31.4
visit = 2024031500123
"""

CSV = """path,layout,psf,background,zero_point,visit,detector,band
D00154912_r_c12_immasked.fits.fz,des,D00154912_r_c12_psfexcat.psf,D00154912_r_c12_bkg.fits.fz,,,,
calexp_R22_S11.fits,lsst,calexp_R22_S11.piff,,31.4,2024031500123,,
"""


@pytest.mark.parametrize("form", ["toml", "csv", "json"])
def test_manifest_forms_agree(tmp_path, form):
    reference = read_manifest(_write(tmp_path / "m.toml", TOML))
    if form == "toml":
        manifest = reference
    elif form == "csv":
        manifest = read_manifest(_write(tmp_path / "m.csv", CSV))
    else:
        manifest = read_manifest(_write(tmp_path / "m.json", reference.model_dump_json()))
    assert manifest == reference
    first, second = manifest.exposures
    assert (first.layout, first.background, first.zero_point) == (
        "des",
        reference.exposures[0].background,
        None,
    )
    assert (second.layout, second.zero_point, second.visit) == ("lsst", 31.4, 2024031500123)


@pytest.mark.parametrize(
    ("name", "text", "message"),
    [
        ("bad.toml", "[[exposures]]\npath = 'a.fits'\nlayuot = 'des'\n", "layuot"),
        ("bad.toml", "[[exposures]\n", "not a valid manifest"),
        ("bad.csv", "path,zero_point\na.fits,thirty\n", "line 2"),
        ("bad.json", '{"exposures": []}', "exposures"),
        ("bad.yaml", "exposures: []", ".toml or .json"),
    ],
)
def test_bad_manifests_name_the_file_and_the_problem(tmp_path, name, text, message):
    path = _write(tmp_path / name, text)
    with pytest.raises(CellCoaddFormatError, match=message) as info:
        read_manifest(path)
    assert str(path) in str(info.value)


def test_config_file_round_trip_and_unknown_keys(tmp_path):
    custom = BuildConfig(n_noise=5, bad_mask_bits=("BADPIX_CRAY",), noise_variance="pixel")
    path = _write(tmp_path / "build.toml", build_config_toml(custom))
    assert read_build_config(path) == custom
    assert read_build_config(_write(tmp_path / "b.json", custom.model_dump_json())) == custom
    with pytest.raises(ConfigError, match=r"b2.toml.*n_nosie"):
        read_build_config(_write(tmp_path / "b2.toml", "n_nosie = 4\n"))
    with pytest.raises(ConfigError, match="psf_size"):
        read_build_config(_write(tmp_path / "b3.json", json.dumps({"psf_size": 34})))


def test_config_command_prints_a_file_build_reads(tmp_path):
    runner = CliRunner()
    shown = runner.invoke(cli, ["config", "--show"])
    assert shown.exit_code == 0, shown.output
    path = _write(tmp_path / "build.toml", shown.output)
    assert read_build_config(path) == BuildConfig()
    checked = runner.invoke(cli, ["config", "--check", str(path), "--json"])
    assert json.loads(checked.output) == json.loads(BuildConfig().model_dump_json())
    bad = runner.invoke(cli, ["config", "--check", str(_write(tmp_path / "x.toml", "k = 1\n"))])
    assert bad.exit_code == 1 and "x.toml" in _message(bad)


@pytest.mark.parametrize(
    ("out", "message"),
    [
        ("missing-dir/patch.fits", "does not exist"),
        ("patch.png", "unsupported file name"),
        ("patch[1].fits", "not allowed"),
        ("!patch.fits", "not allowed"),
    ],
)
def test_build_refuses_bad_outputs_before_work(tmp_path, out, message):
    manifest = _write(tmp_path / "m.toml", TOML)  # its files do not exist: never reached
    result = CliRunner().invoke(
        cli,
        ["build", "--manifest", str(manifest), "--tract", "0", "--patch", "0,0"]
        + ["--out", str(tmp_path / out)],
    )
    assert result.exit_code != 0 and message in _message(result), _message(result)


def test_build_names_an_unreadable_manifest_entry_before_work(tmp_path):
    manifest = _write(tmp_path / "m.toml", TOML)
    result = CliRunner().invoke(
        cli,
        ["build", "--manifest", str(manifest), "--tract", "0", "--patch", "0,0"]
        + ["--out", str(tmp_path / "patch.h5")],
    )
    assert result.exit_code != 0
    assert "D00154912_r_c12_psfexcat.psf" in _message(result)  # the first missing file
    assert not (tmp_path / "patch.h5").exists()


def _message(result) -> str:
    """What the user reads: click's message, or the one line the entry point prints for
    any other error (see cellcoadd.cli.main.main)."""
    return result.output + (str(result.exception) if result.exception else "")


def _write(path, text):
    path.write_text(text)
    return path
