"""simulate -> build -> info -> convert -> show -> trim through the command line."""

import json

from click.testing import CliRunner

import cellcoadd
from cellcoadd.cli.main import cli


def test_command_line_pipeline(tmp_path):
    runner = CliRunner()
    sim = tmp_path / "sim"
    result = runner.invoke(
        cli, ["simulate", "--mode", "field", "--out", str(sim), "--visits", "2", "--quiet"]
    )
    assert result.exit_code == 0, result.output
    exposures = sorted(str(p) for p in sim.glob("visit*-det*.fits"))
    out = tmp_path / "patch.h5"
    args = [
        "build",
        *exposures,
        "--skymap",
        str(sim / "skymap.json"),
        "--tract",
        "0",
        "--patch",
        "1,1",
        "--out",
        str(out),
        "--n-noise",
        "1",
        "--psf-corners",
        "--quiet",
    ]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert "wrote" in result.output
    # refuses to overwrite, with a one-line message
    again = runner.invoke(cli, args)
    assert again.exit_code != 0 and "exists" in again.output

    info = json.loads(runner.invoke(cli, ["info", str(out), "--json"]).output)
    assert info["cells"]["total"] == len(cellcoadd.read(out).cells) == 36
    assert info["n_noise"] == 1
    # --psf-corners: the coadd PSF at the inner corners too, so psf_at interpolates
    cell = next(c for c in cellcoadd.read(out).cells.values() if not c.is_empty)
    assert cell.psf_corners is not None and cell.psf_corners.shape[0] == 4
    border = cell.inner_bbox.x_start - cell.outer_bbox.x_start
    near_corner = cell.psf_at(border + 5.0, border + 5.0)
    assert near_corner.shape == cell.psf.shape and abs(near_corner.sum() - 1.0) < 1e-6
    converted = tmp_path / "patch.fits"
    result = runner.invoke(cli, ["convert", str(out), str(converted)])
    assert result.exit_code == 0, result.output
    assert cellcoadd.read(out).equals(cellcoadd.read(converted))

    coadd = cellcoadd.read(out)
    index = max(coadd.inner_cell_indices, key=lambda i: coadd[i].n_used)
    png = tmp_path / "cell.png"
    result = runner.invoke(
        cli, ["show", str(converted), "--cell", f"{index[0]},{index[1]}", "--out", str(png)]
    )
    assert result.exit_code == 0, result.output
    assert png.read_bytes()[:4] == b"\x89PNG"

    trimmed = tmp_path / "trimmed.fits"
    result = runner.invoke(
        cli,
        [
            "trim",
            str(sim / "truth.fits"),
            "--coadd",
            str(out),
            "--skymap",
            str(sim / "skymap.json"),
            "--out",
            str(trimmed),
        ],
    )
    assert result.exit_code == 0, result.output
    from astropy.table import Table

    table = Table.read(trimmed)
    assert {"is_cell_inner", "is_patch_inner", "is_tract_inner", "is_primary"} <= set(
        table.colnames
    )
    assert table["is_primary"].sum() == table["is_patch_inner"].sum() > 0
