"""Atomic writes (cellcoadd.io._files.atomic): concurrent writers of a new file without overwrite
give one file and one clear error; a failed write leaves the previous file and no
temporary file."""

from __future__ import annotations

import multiprocessing
import os
import threading
from pathlib import Path

import pytest
from coadd_factory import SMALL, make_patch
from exposure_factory import make_exposure

from cellcoadd.io import api
from cellcoadd.io._files.atomic import atomic_write
from cellcoadd.io.exposures import exposure_io
from cellcoadd.io.exposures.exposure_io import read_exposure, write_exposure

#: Seconds a writer waits for the other one before giving up (never reached when correct).
_TIMEOUT = 120


def _exposure(visit: int):
    return make_exposure((30.0, -10.0), shape=(40, 40), visit=visit)


def _race_writer(kind: str, target: str, seed: int, barrier, results) -> None:
    """Write ``target`` without overwrite once both writers have their file complete.

    Runs in its own process: ``_fsync_file`` (called between writing the temporary file
    and publishing it) waits for the other writer, so both have passed the up-front
    existence check before either publishes.
    """
    from cellcoadd.io._files import atomic

    fsync = atomic._fsync_file

    def fsync_then_wait(path: Path) -> None:
        fsync(path)
        barrier.wait(_TIMEOUT)

    atomic._fsync_file = fsync_then_wait
    try:
        if kind == "coadd":
            api.write(make_patch(SMALL, seed=seed), target)
        else:
            write_exposure(_exposure(seed), target)
    except Exception as err:
        results.put((seed, type(err).__name__, str(err)))
    else:
        results.put((seed, "ok", ""))


@pytest.mark.parametrize("name", ["patch.fits", "patch.h5", "exposure.fits"])
def test_concurrent_writers_of_a_new_file(tmp_path, name):
    kind = "exposure" if name.startswith("exposure") else "coadd"
    target = tmp_path / name
    context = multiprocessing.get_context("spawn")
    barrier, results = context.Barrier(2), context.Queue()
    writers = [
        context.Process(target=_race_writer, args=(kind, str(target), seed, barrier, results))
        for seed in (1, 2)
    ]
    for writer in writers:
        writer.start()
    outcomes = sorted((results.get(timeout=2 * _TIMEOUT) for _ in writers), key=lambda r: r[1])
    for writer in writers:
        writer.join(_TIMEOUT)
    assert [outcome[1] for outcome in outcomes] == ["CellCoaddFileExistsError", "ok"], outcomes
    assert f"{target} exists; pass overwrite=True" in outcomes[0][2]
    winner = outcomes[1][0]
    if kind == "coadd":
        assert api.read(target).equals(make_patch(SMALL, seed=winner))
    else:
        assert read_exposure(target).visit == winner
    assert os.listdir(tmp_path) == [name]  # the loser's temporary file is gone


def test_concurrent_threads_with_atomic_write(tmp_path):
    target = tmp_path / "file.bin"
    barrier = threading.Barrier(2)
    outcomes: dict[int, str] = {}

    def writer(number: int) -> None:
        def write(path: Path) -> None:
            path.write_bytes(bytes([number]) * 1000)
            barrier.wait(_TIMEOUT)  # both are past the existence check

        try:
            atomic_write(target, write)
            outcomes[number] = "ok"
        except FileExistsError:
            outcomes[number] = "exists"

    threads = [threading.Thread(target=writer, args=(n,)) for n in (1, 2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(_TIMEOUT)
    assert sorted(outcomes.values()) == ["exists", "ok"]
    winner = next(n for n, outcome in outcomes.items() if outcome == "ok")
    assert target.read_bytes() == bytes([winner]) * 1000
    assert os.listdir(tmp_path) == ["file.bin"]


class Boom(RuntimeError):
    pass


def _partial_then_fail(patch, path, *, compress):
    Path(path).write_bytes(b"partial")
    raise Boom("failed mid-write")


def _fail(*args, **kwargs):
    raise Boom("failed mid-write")


@pytest.mark.parametrize("name", ["patch.fits", "patch.h5", "exposure.fits"])
def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch, name):
    target = tmp_path / name
    if name.startswith("exposure"):
        write_exposure(_exposure(1), target)
        # the temporary file is complete when this fails
        monkeypatch.setattr(exposure_io, "stabilise_fits_checksums", _fail)
    else:
        api.write(make_patch(SMALL, seed=1), target)
        monkeypatch.setitem(api._WRITERS, api.file_format(target), _partial_then_fail)
    before = target.read_bytes()
    with pytest.raises(Boom, match="failed mid-write"):
        if name.startswith("exposure"):
            write_exposure(_exposure(2), target, overwrite=True)
        else:
            api.write(make_patch(SMALL, seed=2), target, overwrite=True)
    assert target.read_bytes() == before
    assert os.listdir(tmp_path) == [name]


def test_atomic_write_failures(tmp_path):
    target = tmp_path / "file.bin"
    target.write_bytes(b"old")
    calls = []

    def write(path: Path) -> None:
        path.write_bytes(b"new, partly")
        raise Boom("failed mid-write")

    with pytest.raises(Boom):
        atomic_write(target, write, overwrite=True, on_failure=lambda: calls.append(1))
    assert calls == [1]
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == ["file.bin"]

    def refuse(temporary: Path) -> None:
        assert temporary.parent == tmp_path and not temporary.exists()
        raise ValueError("refused up front")

    with pytest.raises(ValueError, match="refused up front"):
        atomic_write(target, write, overwrite=True, prepare=refuse)
    with pytest.raises(FileExistsError, match="pass overwrite=True"):
        atomic_write(target, write)
    with pytest.raises(FileNotFoundError, match="no such directory"):
        atomic_write(tmp_path / "missing" / "file.bin", write)
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == ["file.bin"]
    assert atomic_write(target, lambda p: p.write_bytes(b"new"), overwrite=True) == target
    assert target.read_bytes() == b"new" and os.listdir(tmp_path) == ["file.bin"]
