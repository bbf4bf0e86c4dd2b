"""Survey runs: planned from an exposure index, built patch by patch (here or on a dask
LocalCluster), byte-identical to `cellcoadd build`, resumable after kill -9, retried,
failing patches named, stale patches rebuilt, one run per output directory. The
one-tract, one-band field of `run_factory` (band r)."""

from __future__ import annotations

import filecmp
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import fitsio
import pytest
from click.testing import CliRunner
from run_factory import BUILD, skymap, write_field

from cellcoadd.cli.main import cli
from cellcoadd.errors import RunLockedError
from cellcoadd.io import api
from cellcoadd.io.exposures.index import ExposureIndex, FileStamp, absolute_entry
from cellcoadd.model.manifest import ManifestEntry
from cellcoadd.pipelines.survey import PatchKey, plan_tract, run_tract
from cellcoadd.pipelines.survey.ledger import Ledger, RunLock

REPO = Path(__file__).resolve().parents[1]


def _index(db: Path, paths) -> None:
    with ExposureIndex(db) as index:
        update = index.update([absolute_entry(ManifestEntry(path=str(p)), ".") for p in paths])
        assert not update.bad, update.bad


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """Input files, their index, the sky map and build config files, and a reference run."""
    root = tmp_path_factory.mktemp("field")
    paths = write_field(root / "inputs", n_visits=3)
    _index(root / "inputs.sqlite", paths)
    (root / "skymap.json").write_text(skymap().to_json())
    (root / "build.json").write_text(BUILD.model_dump_json())
    result = run_tract(
        root / "inputs.sqlite", skymap(), 0, root / "reference", config=BUILD, progress=False
    )
    assert len(result.built) == 9 and not result.failed
    return root


def _copy_field(field: Path, tmp_path: Path) -> Path:
    """A private copy of the inputs and their index (for tests that change files)."""
    shutil.copytree(field / "inputs", tmp_path / "inputs")
    paths = sorted((tmp_path / "inputs").glob("*.fits"))
    _index(tmp_path / "inputs.sqlite", paths)
    shutil.copy(field / "skymap.json", tmp_path / "skymap.json")
    shutil.copy(field / "build.json", tmp_path / "build.json")
    return tmp_path


def _run_args(root: Path, out: Path, *extra: str) -> list[str]:
    return [
        "run", "--index", str(root / "inputs.sqlite"), "--skymap", str(root / "skymap.json"),
        "--tract", "0", "--out-dir", str(out), "--config", str(root / "build.json"), "-q",
        "--no-figure", *extra,
    ]  # fmt: skip


def _same_outputs(a: Path, b: Path) -> list[str]:
    """Names of the patch files of ``a`` that differ from those of ``b``."""
    a, b = a / "r" / "tract_0", b / "r" / "tract_0"
    names = sorted(p.name for p in a.glob("patch_*"))
    assert set(names) <= {p.name for p in b.glob("patch_*")}
    return [n for n in names if not filecmp.cmp(a / n, b / n, False)]


def _patches(keys) -> set[tuple[int, int]]:
    """The ``(px, py)`` of patch keys (band r, tract 0)."""
    keys = list(keys)
    assert all(k.band == "r" and k.tract == 0 for k in keys), keys
    return {k.patch for k in keys}


def _key(px: int, py: int) -> PatchKey:
    return PatchKey("r", 0, px, py)


def test_run_is_byte_identical_to_build_and_reports(field, tmp_path):
    ref = field / "reference"
    with Ledger(ref) as ledger:
        rows = ledger.records(tract=0)
    assert {row.state.value for row in rows.values()} == {"done"} and len(rows) == 9
    row = rows[_key(1, 0)]
    # `cellcoadd build` of that patch, same inputs in the ledger's order, config and seed
    paths = [stamp.path for stamp in row.inputs]
    out = tmp_path / "built.fits"
    args = ["build", *paths, "--skymap", str(field / "skymap.json"), "--tract", "0"]
    args += ["--patch", "1,0", "--out", str(out), "--config", str(field / "build.json"), "-q"]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert row.output == "r/tract_0/patch_1_0.fits"  # relative to the output directory
    assert out.read_bytes() == (ref / row.output).read_bytes()
    report = json.loads((ref / "report.json").read_text())
    assert report["totals"]["done"] == 9 and report["totals"]["failed"] == 0
    assert report["totals"]["cells"] == 9 * 16
    assert report["bands"]["r"]["done"] == 9 and report["tracts"]["r/0"]["done"] == 9
    tract_report = json.loads((ref / report["tracts"]["r/0"]["report"]).read_text())
    entry = next(p for p in tract_report["patches"] if p["patch"] == [1, 0])
    assert entry["inputs"] == len(paths) and 0 < entry["inputs_used"] <= len(paths)
    assert entry["cpu_s"] > 0 and entry["wall_s"] > 0 and entry["checksum"] == row.checksum
    assert set(entry["rejected_records"]) <= {"edge", "no_overlap", "masked", "bad_psf"}
    assert (ref / "r" / "tract_0" / "coverage.png").read_bytes()[:4] == b"\x89PNG"
    # the same run again: nothing to do
    again = run_tract(field / "inputs.sqlite", skymap(), 0, ref, config=BUILD, progress=False)
    assert not again.built and len(again.up_to_date) == 9


def test_plan_assigns_inputs_to_the_patches_they_may_touch(field):
    with ExposureIndex(field / "inputs.sqlite", readonly=True) as index:
        (plan,) = plan_tract(index, skymap(), 0)
        (only,) = plan_tract(index, skymap(), 0, patches=[(1, 1)])
    assert [p.index for p in plan.patches] == [(x, y) for y in range(3) for x in range(3)]
    assert plan.band == "r" and all(p.inputs for p in plan.patches)
    assert [p.index for p in only.patches] == [(1, 1)]
    assert only.patches[0].inputs == plan.patches[4].inputs
    # the centre patch: every input; a corner patch: not those of the far side
    assert len(plan.patches[4].inputs) == 3 * 9
    with ExposureIndex(field / "inputs.sqlite", readonly=True) as index:
        corner = {(r.visit, r.detector) for r in index.by_ids(plan.patches[0].rows)}
    assert corner == {(v, d) for v in range(3) for d in (0, 1, 3, 4)}


def test_cell_costs_count_the_inputs_each_cell_accepts(field):
    """The cost estimated from the index alone (no file opened) counts, for each cell,
    the inputs whose footprint covers its outer box: those the build may use. Here every
    cell uses all of them (bar inputs masked on the cell), and never one more."""
    with ExposureIndex(field / "inputs.sqlite", readonly=True) as index:
        (plan,) = plan_tract(index, skymap(), 0)
    with Ledger(field / "reference") as ledger:
        rows = ledger.records(tract=0)
    equal = total = 0
    for item in plan.patches:
        costs = item.cell_costs()
        assert set(costs) == {cell.index for cell in item.patch.cells}
        for cx, cy, used in rows[_key(*item.index)].summary.depth:
            assert used <= costs[(cx, cy)] - 1 <= len(item.inputs)
            equal += used == costs[(cx, cy)] - 1
            total += 1
    assert total == 9 * 16 and equal >= 0.9 * total
    # the corner patch's cells far from the tract centre see fewer inputs than those near it
    corner = plan.patches[0].cell_costs()
    assert len(set(corner.values())) > 1


def test_cell_costs_of_a_footprint_covering_part_of_a_patch():
    """A rotated footprint (either winding) counts for the cells whose outer box it
    holds whole, not for those it only overlaps."""
    import numpy as np

    from cellcoadd.pipelines.survey import PatchPlan

    patch = skymap()[0].patch(1, 1)
    cells = {cell.index: cell.outer_bbox for cell in patch.cells}
    left = min(b.x_start for b in cells.values()) - 0.5
    right = max(b.x_stop for b in cells.values()) - 0.5
    bottom = min(b.y_start for b in cells.values()) - 0.5
    top = max(b.y_stop for b in cells.values()) - 0.5
    middle = 0.5 * (left + right)
    # a quad over the left half of the patch, slightly rotated, in both windings
    quad = np.array([[left - 5, bottom - 5], [middle, bottom - 4], [middle, top + 4],
                     [left - 5, top + 5]])  # fmt: skip
    for footprint in (quad, quad[::-1]):
        plan = PatchPlan(_key(1, 1), patch, (), footprints=(footprint,))
        costs = plan.cell_costs()
        for index, box in cells.items():
            held = box.x_stop - 0.5 <= middle
            assert costs[index] == (2.0 if held else 1.0), (index, box)
    assert set(PatchPlan(_key(1, 1), patch, ()).cell_costs().values()) == {1.0}


def test_plan_gives_one_plan_per_band_of_the_tract(tmp_path):
    from exposure_factory import make_wcs

    from cellcoadd.errors import ConfigError
    from cellcoadd.geometry.box import Box
    from cellcoadd.model.maskbits import MaskBits
    from cellcoadd.model.sources import ExposureHeader

    tract = skymap()[0]
    with ExposureIndex(tmp_path / "inputs.sqlite") as index:
        for visit, band in enumerate("rig"):
            wcs = make_wcs(tract.center, (100, 100), 0.2)
            header = ExposureHeader(visit, 0, band, wcs, (100, 100), Box.from_shape((100, 100)),
                                    30.0, MaskBits())  # fmt: skip
            index.put(ManifestEntry(path=f"/data/v{visit}.fits"), header,
                      [FileStamp(f"/data/v{visit}.fits", 1, 1)])  # fmt: skip
        index.commit()
        plans = plan_tract(index, skymap(), 0)
        (plan,) = plan_tract(index, skymap(), 0, bands=["i"])
    assert [p.band for p in plans] == ["g", "i", "r"]
    assert plan.band == "i" and plan.patches
    assert all(len(p.inputs) == 1 for p in plan.patches)  # only visit 1 (band i)
    assert all(p.key.band == "i" for p in plan.patches)
    # a patch asked for that no input of the band touches: planned without inputs
    with ExposureIndex(tmp_path / "inputs.sqlite", readonly=True) as index:
        (far,) = plan_tract(index, skymap(), 0, patches=[(0, 0)], bands=["z"])
    assert [(p.index, p.inputs) for p in far.patches] == [((0, 0), ())]
    # a band the index does not have is refused by a run, naming the bands it has
    with pytest.raises(ConfigError, match=r"band\(s\) \['z'\].*\['g', 'i', 'r'\]"):
        run_tract(tmp_path / "inputs.sqlite", skymap(), 0, tmp_path / "out", band="z")


def test_seed_and_input_changes_rebuild_exactly_the_affected_patches(field, tmp_path):
    root = _copy_field(field, tmp_path)
    out = tmp_path / "out"
    some = [(0, 0), (1, 1), (2, 2)]

    def run(**options):
        options = {"config": BUILD, "patches": some, "progress": False, "figure": False, **options}
        return run_tract(root / "inputs.sqlite", skymap(), 0, out, **options)

    assert len(run().built) == 3
    assert not _same_outputs(out, field / "reference")
    # an input file changes (new mtime) and is indexed again: its patches only
    with Ledger(out) as ledger:
        rows = ledger.records(tract=0)
    touched = root / "inputs" / "visit2-det0.fits"
    users = {k.patch for k, r in rows.items() if str(touched) in {f.path for f in r.inputs}}
    assert users == {(0, 0), (1, 1)}
    stamp = FileStamp.of(str(touched))
    os.utime(touched, ns=(stamp.mtime_ns + 10**9,) * 2)
    _index(root / "inputs.sqlite", sorted((root / "inputs").glob("*.fits")))
    second = run()
    assert _patches(second.built) == users and _patches(second.up_to_date) == {(2, 2)}
    # another seed: every patch, and different bytes
    assert len(run(seed=7).built) == 3
    assert len(_same_outputs(out, field / "reference")) == 3
    # another configuration: every patch again; the same again: none
    config = BUILD.model_copy(update={"n_noise": 2})
    assert len(run(config=config, seed=7).built) == 3
    assert not run(config=config, seed=7).built


def test_changed_input_not_indexed_again_fails_its_patches(field, tmp_path):
    root = _copy_field(field, tmp_path)
    touched = root / "inputs" / "visit1-det3.fits"
    stamp = FileStamp.of(str(touched))
    os.utime(touched, ns=(stamp.mtime_ns + 10**9,) * 2)  # changed after indexing
    result = run_tract(
        root / "inputs.sqlite", skymap(), 0, tmp_path / "out", config=BUILD, retries=0,
        patches=[(1, 1), (2, 0)], progress=False, figure=False,
    )  # fmt: skip
    assert _patches(result.failed) == {(1, 1)} and _patches(result.built) == {(2, 0)}
    assert all("visit1-det3.fits" in why for why in result.failed.values())
    assert all("index" in why for why in result.failed.values())


def test_damaged_input_fails_its_patches_names_the_file_and_exits_non_zero(field, tmp_path):
    root = _copy_field(field, tmp_path)
    damaged = root / "inputs" / "visit0-det0.fits"
    pristine = damaged.read_bytes()
    stamp = FileStamp.of(str(damaged))
    with fitsio.FITS(str(damaged)) as fits_file:
        start = fits_file["META"].get_offsets()["data_start"]
    data = bytearray(pristine)
    data[start + 100 : start + 164] = bytes(64)  # META: every read verifies it
    damaged.write_bytes(bytes(data))
    os.utime(damaged, ns=(stamp.mtime_ns, stamp.mtime_ns))  # as indexed: only reading finds it
    out = tmp_path / "out"
    some = ["--patch", "0,0", "--patch", "2,2"]
    result = CliRunner().invoke(cli, [*_run_args(root, out, *some), "--retries", "1"])
    assert result.exit_code == 1
    report = json.loads((out / "report.json").read_text())
    failed = {tuple(f["patch"]) for f in report["failures"]}
    with Ledger(out) as ledger:
        users = {
            k.patch
            for k, r in ledger.records(tract=0).items()
            if str(damaged) in {f.path for f in r.inputs}
        }
    assert failed == users == {(0, 0)}  # visit0-det0 cannot touch patch 2,2
    assert report["totals"]["done"] == 1
    for item in report["failures"]:
        assert "visit0-det0.fits" in item["error"]
        assert f"r tract 0 patch {item['patch'][0]},{item['patch'][1]}:" in str(result.exception)
    patches = json.loads((out / "r" / "tract_0" / "report.json").read_text())["patches"]
    failed_entries = [p for p in patches if p["state"] == "failed"]
    assert failed_entries and all(p["attempts"] == 2 for p in failed_entries)
    assert all("visit0-det0.fits" in p["retried"][0] for p in failed_entries)
    for px, py in failed:
        assert not (out / "r" / "tract_0" / f"patch_{px}_{py}.fits").exists()
    # the file repaired: only the failed patches are built, identical to the reference
    damaged.write_bytes(pristine)
    os.utime(damaged, ns=(stamp.mtime_ns, stamp.mtime_ns))
    again = run_tract(
        root / "inputs.sqlite", skymap(), 0, out, config=BUILD, patches=[(0, 0), (2, 2)],
        progress=False,
    )  # fmt: skip
    assert _patches(again.built) == failed and _patches(again.up_to_date) == {(2, 2)}
    assert not again.failed
    assert not _same_outputs(out, field / "reference")


def test_a_second_run_on_the_same_directory_is_refused(field, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    with RunLock(out, "cellcoadd run (the first)"):
        result = CliRunner().invoke(cli, _run_args(field, out))
        assert result.exit_code == 1 and isinstance(result.exception, RunLockedError)
        message = str(result.exception)
        assert "another run is using this directory" in message and str(out) in message
        assert f"pid {os.getpid()}" in message and "the first" in message
        with pytest.raises(RunLockedError):
            run_tract(field / "inputs.sqlite", skymap(), 0, out, config=BUILD, progress=False)
    # released: the run goes ahead
    assert CliRunner().invoke(cli, _run_args(field, out, "--patch", "2,2")).exit_code == 0


def _cli_process(args: list[str]) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen(
        [sys.executable, "-m", "cellcoadd", *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,  # its own process group: the run and its workers
    )


def _done_patches(out: Path) -> int:
    try:
        with sqlite3.connect(out / "ledger.sqlite", timeout=5) as db:
            return db.execute("SELECT COUNT(*) FROM patches WHERE state = 'done'").fetchone()[0]
    except sqlite3.Error:
        return 0


@pytest.mark.parametrize("workers", ["1", pytest.param("2", marks=pytest.mark.slow)])
def test_kill_9_of_the_run_then_the_same_command_gives_identical_bytes(field, tmp_path, workers):
    out = tmp_path / "out"
    args = _run_args(field, out, "--workers", workers)
    first = _cli_process(args)
    deadline = time.monotonic() + 300
    while _done_patches(out) < 1 and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert first.poll() is None, first.stdout.read().decode() if first.stdout else ""
    # a second run on the same directory meanwhile is refused, naming the first
    refused = CliRunner().invoke(cli, args)
    assert refused.exit_code == 1 and isinstance(refused.exception, RunLockedError)
    assert f"pid {first.pid}," in str(refused.exception)
    os.killpg(first.pid, signal.SIGKILL)  # the whole run, workers included
    first.wait()
    done_before = _done_patches(out)
    assert 1 <= done_before < 9  # killed mid-way
    second = _cli_process(args)
    output = second.communicate(timeout=600)[0].decode()
    assert second.returncode == 0, output
    assert f"{9 - done_before} built, {done_before} up to date, 0 failed" in output
    assert not _same_outputs(out, field / "reference")
    assert not [p.name for p in (out / "r" / "tract_0").iterdir() if ".tmp-" in p.name]
    with Ledger(out) as ledger:
        assert {row.state.value for row in ledger.records(tract=0).values()} == {"done"}


def test_a_worker_killed_mid_patch_is_retried_on_a_local_cluster(field, tmp_path):
    pytest.importorskip("distributed")
    from cellcoadd.execution import local_cluster

    client, close = local_cluster(2)
    try:
        pids = client.run(os.getpid)
        killed: list[str] = []

        def kill_a_busy_worker() -> None:
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                busy = [  # a worker building a patch (not planning)
                    w
                    for w, keys in client.processing().items()
                    if any(str(k).startswith("cellcoadd-patch") for k in keys)
                ]
                if busy:
                    time.sleep(0.2)  # mid-patch
                    os.kill(pids[busy[0]], signal.SIGKILL)
                    killed.append(busy[0])
                    return
                time.sleep(0.02)

        killer = threading.Thread(target=kill_a_busy_worker)
        killer.start()
        result = run_tract(
            field / "inputs.sqlite", skymap(), 0, tmp_path / "out", config=BUILD,
            patches=[(0, 0), (1, 0), (0, 1), (1, 1)], scheduler=client, progress=False,
            figure=False,
        )  # fmt: skip
        killer.join()
    finally:
        close()
    assert killed and result.retries >= 1 and not result.failed and len(result.built) == 4
    assert killed[0] in result.workers_left  # the run names the worker it lost
    with Ledger(tmp_path / "out") as ledger:
        records = ledger.records(tract=0).values()
    assert max(row.attempts for row in records) >= 2
    # the lost worker is named in the record of the patch it was building
    assert any("KilledWorker" in why or "died" in why for r in records for why in r.retried)
    assert not _same_outputs(tmp_path / "out", field / "reference")


def test_des_files_from_a_manifest_run_byte_identical_to_build(tmp_path):
    """Survey files (DES layout: the real DECam TPV header, PSFEx model, weight map, DESDM
    mask bits) listed in a manifest: indexed, run, and built by `cellcoadd build`."""
    from conftest import DES_PSF
    from test_survey_readers import (
        DES_NX,
        DES_NY,
        des_planes,
        des_tpv_wcs,
        write_des,
    )

    from cellcoadd import BuildConfig, SkyMap, SkyMapConfig
    from cellcoadd.io import DES_BAD_MASK_BITS

    paths = [
        write_des(tmp_path / f"D{v:08d}_c12.fits", des_planes(seed=v), shift=shift)
        for v, shift in enumerate([(0.0, 0.0), (40.3, -25.7)])
    ]
    manifest = tmp_path / "des.toml"
    manifest.write_text(
        "".join(
            f'[[exposures]]\npath = "{p.name}"\nlayout = "des"\npsf = "{DES_PSF}"\n'
            f"zero_point = 30.0\nvisit = {v}\n\n"
            for v, p in enumerate(paths)
        )
    )
    (ra,), (dec,) = des_tpv_wcs().all_pix2world([DES_NX / 2], [DES_NY / 2], 0)
    config = SkyMapConfig(
        pixel_scale=0.2, cell_inner=40, cell_border=10, cells_per_patch=2, patches_per_tract=2
    )
    (tmp_path / "skymap.json").write_text(SkyMap.from_centers([(ra, dec)], config).to_json())
    build = BuildConfig(n_noise=1, psf_size=15, bad_mask_bits=DES_BAD_MASK_BITS)
    (tmp_path / "build.json").write_text(build.model_dump_json())
    runner = CliRunner()
    db = tmp_path / "inputs.sqlite"
    result = runner.invoke(cli, ["index", "--manifest", str(manifest), "--db", str(db), "-q"])
    assert result.exit_code == 0 and "2 added" in result.output, result.output
    out = tmp_path / "run"
    result = runner.invoke(cli, _run_args(tmp_path, out, "--patch", "1,0"))
    assert result.exit_code == 0, result.output
    built = tmp_path / "built.fits"
    args = ["build", "--manifest", str(manifest), "--skymap", str(tmp_path / "skymap.json")]
    args += ["--tract", "0", "--patch", "1,0", "--out", str(built)]
    args += ["--config", str(tmp_path / "build.json"), "-q"]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    (band,) = [p.name for p in out.iterdir() if p.is_dir()]  # the DES file's own band
    assert (out / band / "tract_0" / "patch_1_0.fits").read_bytes() == built.read_bytes()
    report = json.loads((out / band / "tract_0" / "report.json").read_text())
    assert report["patches"][0]["inputs_used"] == 2
    # the cost estimate from the TPV footprints in the index bounds what each cell used
    with ExposureIndex(db, readonly=True) as index:
        ((item,),) = (p.patches for p in plan_tract(
            index, SkyMap.from_json((tmp_path / "skymap.json").read_text()), 0, patches=[(1, 0)]
        ))  # fmt: skip
    costs = item.cell_costs()
    with Ledger(out) as ledger:
        depth = ledger.records(tract=0)[PatchKey(band, 0, 1, 0)].summary.depth
    assert all(used <= costs[(cx, cy)] - 1 <= 2 for cx, cy, used in depth)
    assert sum(used == costs[(cx, cy)] - 1 for cx, cy, used in depth) >= 0.5 * len(depth)


def test_workers_without_dask_distributed_is_a_clear_error(field, tmp_path, monkeypatch):
    from cellcoadd.errors import MissingDependencyError

    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed
    with pytest.raises(MissingDependencyError, match=r"pip install 'cellcoadd\[dask\]'"):
        run_tract(
            field / "inputs.sqlite", skymap(), 0, tmp_path / "out", config=BUILD, workers=2,
            patches=[(2, 2)], progress=False, figure=False,
        )  # fmt: skip
    assert not (tmp_path / "out").exists()  # refused before any work


def test_parts_per_patch_keeps_every_worker_busy_to_the_end():
    from cellcoadd.execution import parts_per_task as parts_per_patch

    assert parts_per_patch(9, 2) == [1] * 8 + [2]  # 4.5 patches per worker, not 5 and 4
    assert parts_per_patch(100, 2) == [1] * 100 and parts_per_patch(8, 2) == [1] * 8
    assert parts_per_patch(1, 8) == [8] and parts_per_patch(3, 1) == [1, 1, 1]
    assert parts_per_patch(1, 16) == [8]  # at most 8 parts
    for patches in range(1, 40):
        for workers in (2, 3, 4, 8):
            parts = parts_per_patch(patches, workers)
            assert len(parts) == patches and parts == sorted(parts)  # the cut ones last
            assert sum(parts) % workers == 0  # equal tasks share out evenly


def test_patches_cut_into_parts_on_a_local_cluster_are_byte_identical(field, tmp_path, monkeypatch):
    """Three patches on two workers: two whole, the third cut in two bands of cells, built
    as separate tasks and written by a worker; the files equal those of the serial run.
    Every optional plane is on (psf_corners, ...): the parts carry them all."""
    pytest.importorskip("distributed")
    from cellcoadd.execution import local_cluster
    from cellcoadd.model.planes import optional_plane_flags

    # a stamp the 5-pixel cell border holds at the corners
    config = BUILD.model_copy(
        update={"psf_size": 11, **dict.fromkeys(optional_plane_flags().values(), True)}
    )
    patches = [(0, 0), (1, 1), (2, 2)]
    run_tract(
        field / "inputs.sqlite", skymap(), 0, tmp_path / "serial", config=config,
        patches=patches, progress=False, figure=False,
    )  # fmt: skip

    # a nanny lets this process's environment win over the configuration (as a user's
    # MALLOC_* settings should); an in-process dask worker of another test may have left
    # dask's own values there
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    monkeypatch.delenv("MALLOC_ARENA_MAX", raising=False)
    client, close = local_cluster(2)
    try:
        # the workers run with cellcoadd's settings (heap arrays, no 10 ms profiler)
        settings = client.run(_worker_settings)
        result = run_tract(
            field / "inputs.sqlite", skymap(), 0, tmp_path / "out", config=config,
            patches=patches, scheduler=client, progress=False, figure=False,
        )  # fmt: skip
    finally:
        close()
    assert len(settings) == 2
    assert set(settings.values()) == {("33554432", "268435456", "1", False, "1s")}
    assert not result.failed and _patches(result.built) == set(patches)
    assert not _same_outputs(tmp_path / "out", tmp_path / "serial")
    written = sorted((tmp_path / "out" / "r" / "tract_0").glob("patch_*"))
    assert written
    for path in written:  # every cell of every patch holds every optional plane
        coadd = api.read(path)
        assert set(optional_plane_flags()) <= set(coadd.metadata.cell_plane_names)
        assert all(
            getattr(cell, name) is not None
            for cell in coadd.cells.values()
            for name in optional_plane_flags()
        )
    report = json.loads((tmp_path / "out" / "r" / "tract_0" / "report.json").read_text())
    assert sorted(p["parts"] for p in report["patches"]) == [1, 1, 2]
    assert sorted(len(p["parts_cpu_s"]) for p in report["patches"]) == [1, 1, 2]


def _worker_settings() -> tuple:
    import dask

    return (
        os.environ.get("MALLOC_MMAP_THRESHOLD_"),
        os.environ.get("MALLOC_TRIM_THRESHOLD_"),
        os.environ.get("MALLOC_ARENA_MAX"),
        dask.config.get("distributed.worker.profile.enabled"),
        dask.config.get("distributed.admin.tick.interval"),
    )


def test_worker_environment_gives_dask_the_same_settings():
    """Workers started elsewhere (a job script) get the same configuration from the
    environment variables as the local cluster from DASK_WORKER_CONFIG."""
    import dask

    from cellcoadd.execution import DASK_WORKER_CONFIG, dask_worker_environment

    env = dask_worker_environment()
    assert env.pop("MALLOC_MMAP_THRESHOLD_") == "33554432"
    assert env.pop("MALLOC_TRIM_THRESHOLD_") == "268435456"
    assert env.pop("MALLOC_ARENA_MAX") == "1"
    assert all(name.startswith("DASK_DISTRIBUTED__") and "-" not in name for name in env)
    with dask.config.set(dask.config.collect_env(env)):
        for key, value in DASK_WORKER_CONFIG.items():
            if "pre-spawn-environ" not in key:
                assert dask.config.get(key) == value, key


def test_the_held_back_tasks_are_cut_as_the_whole_run_would_be():
    """Tasks that share out evenly among the workers are never cut, however the held-back
    tail is reached; otherwise only the last ``tasks % workers`` are."""
    pytest.importorskip("distributed")
    from cellcoadd.execution import local_cluster, run_on_dask

    client, close = local_cluster(2)
    try:
        for count, expected in ((8, [1] * 8), (5, [1] * 4 + [2])):
            cuts: dict[int, int] = {}

            def submit(item, attempt, parts, key, cuts=cuts):
                cuts[item] = parts
                return [client.submit(time.sleep, 0.05 * (1 + item % 3), key=key, pure=False)]

            run_on_dask(client, list(range(count)), submit, lambda outcome: None, retries=0)
            assert [cuts[i] for i in range(count)] == expected, count
    finally:
        close()
