"""The exposure index: headers stored once, footprints queried, files added, changed and
deleted, bad files recorded, queries across RA 0/360 and at the poles."""

from __future__ import annotations

import os
import pickle
import shutil

import numpy as np
import pytest
from click.testing import CliRunner
from exposure_factory import make_wcs
from run_factory import skymap, write_field

from cellcoadd.cli.main import cli
from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.wcs_utils import canonical_wcs
from cellcoadd.io.exposures.exposure_source import ExposureFile
from cellcoadd.io.exposures.index import (
    ExposureIndex,
    FileStamp,
    absolute_entry,
    header_from_json,
    header_to_json,
)
from cellcoadd.model.manifest import ManifestEntry
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.sources import ExposureHeader


def _entries(paths):
    return [absolute_entry(ManifestEntry(path=str(p)), ".") for p in paths]


def _patch_corners(patch):
    box = patch.outer_bbox
    x = np.array([box.x_start, box.x_stop, box.x_stop, box.x_start]) - 0.5
    y = np.array([box.y_start, box.y_start, box.y_stop, box.y_stop]) - 0.5
    ra, dec = patch.tract.pixel_to_sky(x, y)
    return np.column_stack([ra, dec])


def test_stored_header_is_the_files_header_bit_for_bit(tmp_path):
    paths = write_field(tmp_path, n_visits=2)  # visit 1 has a TAN-SIP WCS
    with ExposureIndex(tmp_path / "inputs.sqlite") as index:
        index.update(_entries(paths))
        found = index.query(_patch_corners(skymap()[0].patch(0, 0)))
        assert found and all(row.header_json is None for row in found)  # queries skip it
        rows = index.by_ids([row.id for row in found])
        for row in rows:
            stored = row.header()
            read = ExposureFile(row.path).header()
            assert pickle.dumps(stored.wcs) == pickle.dumps(read.wcs)
            assert (stored.visit, stored.detector, stored.band) == (read.visit, read.detector, "r")
            assert stored.valid_box == read.valid_box and stored.shape == read.shape
            assert stored.mask_bits == read.mask_bits and stored.zero_point == read.zero_point


def test_query_finds_the_inputs_near_each_patch_only(tmp_path):
    paths = write_field(tmp_path, n_visits=1, patches_per_tract=3, shape=(60, 60))
    tract = skymap(3)[0]
    with ExposureIndex(tmp_path / "inputs.sqlite", nside=65536) as index:
        update = index.update(_entries(paths))
        assert len(update.added) == 9 and not update.bad
        corner = index.query(_patch_corners(tract.patch(0, 0)))
        centre = index.query(_patch_corners(tract.patch(1, 1)))
    # detector d is centred on patch d (row-major); small exposures touch only neighbours
    assert 0 in {r.detector for r in corner} and 8 not in {r.detector for r in corner}
    assert {r.detector for r in centre} == set(range(9))


def test_update_adds_changes_and_reports_vanished_and_bad_files(tmp_path):
    paths = write_field(tmp_path / "a", n_visits=1)
    db = tmp_path / "inputs.sqlite"
    with ExposureIndex(db) as index:
        first = index.update(_entries(paths), workers=2)
        assert sorted(first.added) == sorted(os.path.abspath(p) for p in paths)
        again = index.update(_entries(paths))
        assert len(again.unchanged) == 9 and not again.added and not again.updated
        # add two visits, rewrite one file, delete another, add a damaged one
        more = write_field(tmp_path / "a", n_visits=1, start_visit=1)
        changed = paths[2]  # same name, new bytes
        shutil.copyfile(write_field(tmp_path / "b", n_visits=1, start_visit=5)[2], changed)
        stamp = FileStamp.of(str(changed))
        os.utime(changed, ns=(stamp.mtime_ns + 10**9, stamp.mtime_ns + 10**9))
        os.remove(paths[3])
        bad = tmp_path / "a" / "broken.fits"
        bad.write_bytes(b"SIMPLE  =                    T" + b"\0" * 100)
        update = index.update(_entries([*paths[:3], *more, bad]))
        assert update.updated == [os.path.abspath(changed)]
        assert sorted(update.added) == sorted(os.path.abspath(p) for p in more)
        assert update.vanished == [os.path.abspath(paths[3])]
        assert [p for p, _ in update.bad] == [os.path.abspath(bad)]
        assert "broken.fits" in update.bad[0][0] and update.bad[0][1]
        stats = index.stats()
        assert stats["ok"] == 17 and stats["bad"] == 1 and stats["vanished"] == 1
        assert stats["visits"] == 3 and stats["bands"]["r"]["files"] == 17
        listed = dict(index.bad_files())
        assert os.path.abspath(bad) in listed and os.path.abspath(paths[3]) in listed
        everything = index.query(_patch_corners(skymap()[0].patch(0, 0)))
        assert os.path.abspath(paths[3]) not in {r.path for r in everything}


def test_checksum_finds_a_change_that_keeps_size_and_mtime(tmp_path):
    (path,) = write_field(tmp_path, n_visits=1)[:1]
    with ExposureIndex(tmp_path / "inputs.sqlite") as index:
        index.update(_entries([path]), checksum=True)
        stamp = FileStamp.of(str(path))
        data = bytearray(path.read_bytes())
        data[-10] ^= 0xFF
        path.write_bytes(bytes(data))
        os.utime(path, ns=(stamp.mtime_ns, stamp.mtime_ns))
        assert index.update(_entries([path])).unchanged  # size and mtime alone: unchanged
        assert index.update(_entries([path]), checksum=True).bad  # the checksum: re-read


def _synthetic(index, visit, center, shape=(4000, 4000), scale=0.2):
    wcs = make_wcs(center, shape, scale)
    header = ExposureHeader(visit, 0, "i", wcs, shape, Box.from_shape(shape), 31.4, MaskBits())
    entry = ManifestEntry(path=f"/survey/v{visit}.fits")
    index.put(entry, header, [FileStamp(entry.path, 1, 1)])


def _square(ra, dec, half):
    # a small square of side 2 * half deg around (ra, dec), corners in order
    dra = half / max(np.cos(np.radians(dec)), 1e-3)
    return np.array(
        [
            [ra - dra, dec - half],
            [ra + dra, dec - half],
            [ra + dra, dec + half],
            [ra - dra, dec + half],
        ]
    )


def test_queries_across_ra_wrap_and_at_the_poles(tmp_path):
    with ExposureIndex(tmp_path / "inputs.sqlite") as index:
        _synthetic(index, 1, (0.05, 10.0))  # straddles RA 0: 0.22 deg on a side
        _synthetic(index, 2, (359.95, -10.0))
        _synthetic(index, 3, (123.0, 89.99))  # holds the north pole
        _synthetic(index, 4, (300.0, -89.95))  # near the south pole
        _synthetic(index, 5, (180.0, 0.0))
        index.commit()
        assert [r.visit for r in index.query(_square(359.9, 10.0, 0.02))] == [1]
        assert [r.visit for r in index.query(_square(0.08, -10.0, 0.02))] == [2]
        # the pole seen from any RA
        for ra in (0.0, 90.0, 200.0, 359.0):
            assert [r.visit for r in index.query(_square(ra, 89.995, 0.003))] == [3]
        around = np.array([[0.0, -89.9], [90.0, -89.9], [180.0, -89.9], [270.0, -89.9]])
        assert [r.visit for r in index.query(around)] == [4]
        assert index.query(_square(90.0, 0.0, 0.1)) == []
        stats = index.stats()
        assert stats["ok"] == 5 and stats["footprint_area_deg2"] == pytest.approx(5 * 0.04938, 1e-2)


def test_header_json_round_trip_is_exact():
    # headers read from files are canonical (what a trip to another process gives)
    wcs = canonical_wcs(make_wcs((359.99, -45.0), (200, 300), 0.263, rotation_deg=33.0, sip=True))
    header = ExposureHeader(
        7, 12, "z", wcs, (200, 300), Box.from_shape((200, 300)), 30.1, MaskBits()
    )
    again = header_from_json(header_to_json(header))
    x, y = np.meshgrid(np.linspace(-5, 305, 9), np.linspace(-5, 205, 9))
    assert np.array_equal(header.wcs.all_pix2world(x, y, 0), again.wcs.all_pix2world(x, y, 0))
    assert header_to_json(again) == header_to_json(header)


def test_readonly_open_of_a_missing_or_foreign_file_names_it(tmp_path):
    with pytest.raises(CellCoaddFormatError, match="no such exposure index"):
        ExposureIndex(tmp_path / "none.sqlite", readonly=True)
    other = tmp_path / "other.sqlite"
    other.write_bytes(b"not a database" * 100)
    with pytest.raises(CellCoaddFormatError, match="other.sqlite"):
        ExposureIndex(other)


def test_index_and_ledger_paths_go_through_the_path_gate(tmp_path):
    """A FIFO or a directory where an index or a ledger should be is refused, named,
    before SQLite opens it (a FIFO would hang the open); odd characters in a read-only
    index's path are not taken for URI syntax."""
    from cellcoadd.pipelines.survey.ledger import Ledger

    fifo = tmp_path / "inputs.sqlite"
    os.mkfifo(fifo)
    for readonly in (True, False):
        with pytest.raises(CellCoaddFormatError, match=r"inputs\.sqlite.*FIFO"):
            ExposureIndex(fifo, readonly=readonly)
    (tmp_path / "dir.sqlite").mkdir()
    with pytest.raises(CellCoaddFormatError, match="directory"):
        ExposureIndex(tmp_path / "dir.sqlite")
    out = tmp_path / "out"
    (out / "ledger.sqlite").mkdir(parents=True)
    with pytest.raises(CellCoaddFormatError, match=r"ledger\.sqlite.*directory"):
        Ledger(out)
    odd = tmp_path / "odd?mode=rw#x.sqlite"
    with ExposureIndex(odd):
        pass
    with ExposureIndex(odd, readonly=True) as index:
        assert index.stats()["files"] == 0


def test_index_command_updates_and_summarises(tmp_path):
    paths = write_field(tmp_path, n_visits=1)
    db = str(tmp_path / "inputs.sqlite")
    runner = CliRunner()
    bad = tmp_path / "empty.fits"
    bad.write_bytes(b"")
    result = runner.invoke(cli, ["index", *map(str, paths), str(bad), "--db", db, "-q"])
    assert result.exit_code == 1, result.output  # a bad file: not a success
    assert "9 added" in result.output and "1 bad" in result.output and "empty.fits" in result.output
    assert "1 file is bad" in result.output and "--allow-bad" in result.output
    result = runner.invoke(cli, ["index", *map(str, paths), str(bad), "--db", db, "--allow-bad"])
    assert result.exit_code == 0, result.output
    assert "9 unchanged" in result.output and "bad: " in result.output
    result = runner.invoke(cli, ["index", "--db", db, "--stats"])
    assert result.exit_code == 0, result.output
    assert "10 files (9 usable, 1 bad" in result.output and "band r: 9 files" in result.output


def test_a_damaged_row_is_read_again_or_marked_bad_never_trusted(tmp_path):
    """A row that disagrees with its checksum is read again when its file is indexed
    again; otherwise it is marked bad (its identity no longer taken), never left usable.
    A row id moved away from its footprint pixels is named by queries."""
    import sqlite3

    from cellcoadd.errors import IndexRowError

    paths = write_field(tmp_path, n_visits=1)
    db = tmp_path / "inputs.sqlite"
    with ExposureIndex(db) as index:
        index.update(_entries(paths))
    with sqlite3.connect(db) as raw:
        raw.execute("UPDATE exposures SET band = 'z' WHERE path = ?", (str(paths[0]),))
        raw.execute("UPDATE exposures SET band = 'z' WHERE path = ?", (str(paths[1]),))
    raw.close()
    with ExposureIndex(db) as index:
        update = index.update(_entries(paths[:1]))  # paths[1] is not indexed again
        assert update.updated == [str(paths[0])]
        assert update.bad == [(str(paths[1]), update.bad[0][1])]
        assert "its index row was damaged" in update.bad[0][1]
        assert index.stats()["ok"] == 8 and index.bands() == ["r"]
        update = index.update(_entries(paths[1:2]))
        assert update.updated == [str(paths[1])] and not update.bad
        assert index.stats()["ok"] == 9
    with sqlite3.connect(db) as raw:
        raw.execute("UPDATE exposures SET id = 1000 WHERE path = ?", (str(paths[4]),))
    raw.close()
    with ExposureIndex(db, readonly=True) as index:
        with pytest.raises(IndexRowError, match=r"the spatial key lists rows \[\d+\]"):
            index.query(_patch_corners(skymap()[0].patch(1, 1)))
