"""Builds on several workers (process pool, dask): a cell that raises or a worker that
dies is named, the CLI then writes nothing, and files are byte-identical whatever the
executor (see docs/reliability.md). Dask tests run last."""

from __future__ import annotations

import functools
import hashlib
import itertools
import multiprocessing
import os
import re
from pathlib import Path

import fitsio
import pytest
from coadd_factory import (
    TINY_BUILD,
    DyingPsf,
    cell_sized_exposure,
    tiny_exposures,
    tiny_patch,
    tiny_skymap,
)
from hypothesis import given, settings
from hypothesis import strategies as st

import cellcoadd.builder.patch as patch_module
from cellcoadd import BuildConfig, CellBuildError, Exposure, build_patch
from cellcoadd.cli.main import main as cli_main
from cellcoadd.io import api
from cellcoadd.io.exposures.exposure_io import write_exposure
from cellcoadd.model.planes import optional_plane_flags
from cellcoadd.model.psf import GalSimPsf

_DATE = re.compile(rb"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d")


@pytest.fixture(scope="module")
def tiny():
    """The tiny patch, two good exposures and their serial build."""
    patch = tiny_patch()
    good = tiny_exposures(patch, 2)
    return patch, good, build_patch(patch, good, TINY_BUILD, seed=1, progress=False)


# ------------------------------------------------------------------------ dying workers


def _killer(patch) -> Exposure:
    """An exposure used by cell (0, 0) only, whose PSF kills any worker process drawing it."""
    return cell_sized_exposure(patch.tract.cell(0, 0), 50, GalSimPsf(DyingPsf(os.getpid())))


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
    with pytest.raises(CellBuildError, match="ConfigError: psf_size 35 exceeds") as info:
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
    raise RuntimeError("the block builder replaced by a test ran in the parent process")


@pytest.mark.skipif(
    multiprocessing.get_start_method() != "fork",
    reason="the replaced block builder reaches worker processes only when they are forked",
)
def test_cli_build_with_a_dying_worker_writes_nothing(
    tmp_path, exposure_files, capsys, monkeypatch
):
    files, skymap = exposure_files
    monkeypatch.setattr(
        patch_module, "_build_block", functools.partial(_die_in_workers, os.getpid())
    )
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


def test_a_patch_built_in_parts_and_merged_is_the_patch_built_at_once(tmp_path, tiny):
    from cellcoadd.builder.patch import blocks_of, merge_patch_parts
    from cellcoadd.errors import ConfigError, InvalidCoaddError

    patch, good, _ = tiny
    every_plane = TINY_BUILD.model_copy(update=dict.fromkeys(optional_plane_flags().values(), True))
    whole = build_patch(patch, good, every_plane, seed=1, progress=False, workers=2)
    bands = blocks_of(patch.cells, 3)
    assert len(bands) >= 2
    parts = [
        build_patch(
            patch, good, every_plane, seed=1, progress=False, cells=[c.index for c in cells]
        )  # fmt: skip
        for cells in reversed(bands)  # any order
    ]
    assert [len(p.cells) for p in parts] == [len(b) for b in reversed(bands)]
    merged = merge_patch_parts(parts)
    api.write(whole, tmp_path / "whole.fits")
    api.write(merged, tmp_path / "merged.fits")
    assert _sha256(tmp_path / "whole.fits") == _sha256(tmp_path / "merged.fits")
    with pytest.raises(InvalidCoaddError, match="two parts"):
        merge_patch_parts([parts[0], parts[0]])
    with pytest.raises(InvalidCoaddError, match="different metadata"):
        merge_patch_parts([parts[0], build_patch(patch, good, BuildConfig(psf_size=21),
                                                 seed=1, progress=False,
                                                 cells=[bands[0][0].index])])  # fmt: skip
    with pytest.raises(ConfigError, match=r"not cells of patch"):
        build_patch(patch, good, TINY_BUILD, progress=False, cells=[(99, 99)])


def test_parts_cut_by_cost_inside_a_column_merge_into_the_patch_built_at_once(tmp_path, tiny):
    """Parts of equal cost may end inside a column: built and merged, the same bytes."""
    from cellcoadd.builder.patch import merge_patch_parts, parts_by_cost

    patch, good, whole = tiny
    costs = {cell.index: 1.0 + 3.0 * (cell.index[0] % 2) for cell in patch.cells}
    parts = parts_by_cost(patch.cells, costs, 3)
    columns = [{cell.index[0] for cell in part} for part in parts]
    assert len(parts) == 3 and any(a & b for a, b in itertools.pairwise(columns))  # a column cut
    merged = merge_patch_parts(
        [build_patch(patch, good, TINY_BUILD, seed=1, progress=False,
                     cells=[c.index for c in part]) for part in parts]
    )  # fmt: skip
    api.write(whole, tmp_path / "whole.fits")
    api.write(merged, tmp_path / "merged.fits")
    assert _sha256(tmp_path / "whole.fits") == _sha256(tmp_path / "merged.fits")


@settings(max_examples=200, deadline=None)
@given(
    costs=st.lists(st.floats(0.1, 100.0), min_size=1, max_size=60),
    n_parts=st.integers(1, 10),
    columns=st.integers(1, 8),
)
def test_parts_by_cost_are_runs_of_cells_in_file_order_of_about_equal_cost(costs, n_parts, columns):
    from types import SimpleNamespace

    from cellcoadd.builder.patch import parts_by_cost

    cells = [SimpleNamespace(index=(i % columns, i // columns)) for i in range(len(costs))]
    by_index = {cell.index: cost for cell, cost in zip(cells, costs, strict=True)}
    parts = parts_by_cost(cells[::-1], by_index, n_parts)  # any order in
    assert len(parts) == min(n_parts, len(cells)) and all(parts)
    flat = [cell.index for part in parts for cell in part]
    assert flat == sorted(by_index)  # every cell once, runs in file order
    ideal = sum(costs) / len(parts)
    assert max(sum(by_index[c.index] for c in part) for part in parts) <= ideal + max(costs)


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
    """With every optional plane on (psf_corners, ...): each route carries them all."""
    patch, good, _ = tiny
    config = TINY_BUILD.model_copy(update=dict.fromkeys(optional_plane_flags().values(), True))
    builds = {
        "serial": build_patch(patch, good, config, seed=1, progress=False),
        "pool": build_patch(patch, good, config, seed=1, progress=False, workers=2),
        "dask": build_patch(patch, good, config, seed=1, progress=False, scheduler=dask_client),
    }
    for coadd in builds.values():
        assert set(optional_plane_flags()) <= set(coadd.metadata.cell_plane_names)
        assert all(set(cell.plane_names) == set(coadd.metadata.cell_plane_names)
                   for cell in coadd.cells.values())  # fmt: skip
    for name in ("patch.fits", "patch.fits.fz", "patch.h5"):
        digests = {}
        for executor, coadd in builds.items():
            api.write(coadd, tmp_path / f"{executor}-{name}")
            digests[executor] = _sha256(tmp_path / f"{executor}-{name}")
        assert len(set(digests.values())) == 1, (name, digests)


def test_a_raising_cell_on_dask_is_named(tiny, dask_client):
    patch, good, _ = tiny
    config = BuildConfig(n_noise=1, psf_size=35)
    with pytest.raises(CellBuildError, match="ConfigError: psf_size 35 exceeds") as info:
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


def test_a_dead_worker_names_every_cell_of_the_blocks_that_were_running(tiny):
    """The pool fails every unfinished block at once; the one that died may be any of the
    blocks the workers were running (the first unfinished ones): all their cells are named,
    whichever finished first (this depended on timing when only the first was named)."""
    from concurrent.futures import BrokenExecutor, Future

    patch, _, _ = tiny
    blocks = patch_module.blocks_of(patch.cells, 4)  # rows of 4 cells
    futures = []
    for number in range(len(blocks)):
        future: Future = Future()
        if number == 0:
            future.set_result([])  # the first row was built
        else:
            future.set_exception(BrokenExecutor("a worker died"))
        futures.append(future)
    submitted = list(zip(futures, blocks, strict=True))
    message = patch_module._died_message(submitted, BrokenExecutor("a worker died"), 2)
    named = set(re.findall(r"\((-?\d+), (-?\d+)\)", message.split("BrokenExecutor")[0]))
    running = {(str(c.index[0]), str(c.index[1])) for block in blocks[1:3] for c in block}
    assert running <= named and _named_cell(message) == blocks[1][0].index
    assert not {(str(c.index[0]), str(c.index[1])) for c in blocks[3]} & named


@pytest.mark.skipif(not os.uname().sysname == "Linux", reason="forked workers on Linux")
def test_a_local_cluster_forks_its_workers_and_gives_them_the_allocator_settings():
    """Forked workers skip importing everything again; glibc took the environment's
    allocator settings before the fork, so a worker plugin applies them (also to a worker
    the nanny starts again)."""
    pytest.importorskip("distributed")
    from cellcoadd.execution import local_cluster

    client, close = local_cluster(2)
    try:
        seen = client.run(_worker_start, os.getpid())
    finally:
        close()
    assert len(seen) == 2
    for method, plugins, imported, parent in seen.values():
        assert method == "fork" and parent == os.getpid()
        assert "cellcoadd-malloc-settings" in plugins and imported


def _worker_start(parent: int, dask_worker=None) -> tuple:
    import sys

    import dask

    return (
        dask.config.get("distributed.worker.multiprocessing-method"),
        list(dask_worker.plugins),
        "cellcoadd.builder.patch" in sys.modules,  # inherited, not imported again
        os.getppid(),
    )
