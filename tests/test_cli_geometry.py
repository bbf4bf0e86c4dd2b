"""The geometry commands and the one-line error convention."""

import json
import subprocess
import sys

from click.testing import CliRunner

from cellcoadd.cli.main import cli


def test_locate_json_matches_library():
    from cellcoadd import SkyMap

    result = CliRunner().invoke(cli, ["locate", "150.1", "2.2", "--json"])
    assert result.exit_code == 0, result.output
    got = json.loads(result.output)
    want = SkyMap.rings().locate([150.1], [2.2])[0]
    assert got["tract"] == want["tract"] and got["cell_x"] == want["cell_x"]


def test_skymap_writes_json_and_layout(tmp_path):
    out, png = tmp_path / "skymap.json", tmp_path / "layout.png"
    args = ["skymap", "--center", "10,-30", "--cells-per-patch", "4", "--out", str(out)]
    result = CliRunner().invoke(cli, [*args, "--layout", str(png)])
    assert result.exit_code == 0, result.output
    assert "0.50 arcmin" in result.output
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    from cellcoadd import SkyMap

    assert SkyMap.from_json(out.read_text()).config.cells_per_patch == 4


def test_python_dash_m_and_one_line_errors(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    proc = subprocess.run(
        [sys.executable, "-m", "cellcoadd", "locate", "1", "2", "--skymap", str(bad)],
        capture_output=True,
        text=True,
    )
    assert proc.returncode != 0
    assert "not a valid sky map file" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
