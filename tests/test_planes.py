"""The one description of a cell's planes (``cellcoadd.model.planes``) is what the model, both
file formats, the file-size estimate and ``cellcoadd info`` follow."""

from __future__ import annotations

import copy
import dataclasses
import inspect
import json
import os
from pathlib import Path
from typing import get_args

import fitsio
import h5py
import numpy as np
import pytest
from coadd_factory import make_patch

from cellcoadd.cli.storage import patch_summary, stored_planes
from cellcoadd.io import api
from cellcoadd.io.coadd import fits_format, hdf5_format
from cellcoadd.io.coadd.cell_records import expected_shapes
from cellcoadd.model import planes as cell_planes
from cellcoadd.model.cell_coadd import CellCoadd, CellPlanes
from cellcoadd.model.patch_coadd import Plane

#: Keyword arguments of CellCoadd that are not planes.
_NOT_PLANES = {"inputs", "tract", "index", "inner_bbox", "outer_bbox", "wcs", "common"}
#: FITS tile compression of each compression kind (None: not compressed).
_FITS_COMPRESSION = {"float_bits": "GZIP_2", "integer": "RICE_1", "none": None}


def test_description_is_well_formed():
    names = cell_planes.plane_names()
    assert len(set(names)) == len(names)
    assert cell_planes.INPUTS not in names
    assert cell_planes.cell_objects() == (*names, cell_planes.INPUTS)
    for spec in cell_planes.PLANES:
        assert cell_planes.plane(spec.name) is spec
        assert spec.dtype.isnative and spec.stored_dtype.byteorder in "<="
        # float planes keep their bit patterns when compressed; integer ones are integers
        kind = {"f": "float_bits", "i": "integer"}[spec.dtype.kind]
        assert spec.compression in (kind, "none")
        if spec.compression == "float_bits":  # FITS stores them as int32 (CCBITS)
            assert spec.dtype == np.float32
        assert spec.doc
    with pytest.raises(KeyError):
        cell_planes.plane("weight")


def test_model_follows_the_description():
    patch = make_patch(n_noise=3, psf_size=7, psf_corners=True, psf_phase=True)
    cell = next(iter(patch.values()))
    params = set(inspect.signature(CellCoadd).parameters)
    assert params - _NOT_PLANES == set(cell_planes.plane_names())
    for spec in cell_planes.PLANES:
        array = getattr(cell, spec.name)
        assert array.dtype == spec.dtype
        assert array.shape == spec.shape(cell.shape, 3, 7, cell.n_used)
    # (the tuple keeps its historical field order: unpacking it must not change)
    assert set(CellPlanes._fields) == set(cell_planes.grid_plane_names())
    assert set(get_args(Plane)) == set(cell_planes.grid_plane_names())
    inner = cell.inner
    side = patch.metadata.cell_inner
    for name in cell_planes.grid_plane_names():
        assert getattr(inner, name).shape[-2:] == (side, side)
        assert np.shares_memory(getattr(inner, name), getattr(cell, name))
    # every stitchable plane stitches; the stamp does not
    for name in cell_planes.grid_plane_names():
        noise_index = 0 if cell_planes.plane(name).per_realization else None
        stitched = patch.stitch(name, noise_index=noise_index)  # type: ignore[arg-type]
        assert stitched.dtype == cell_planes.plane(name).dtype
    with pytest.raises(ValueError):
        patch.stitch("psf")  # type: ignore[arg-type]
    # equality compares every plane
    for spec in cell_planes.PLANES:
        other = make_patch(n_noise=3, psf_size=7, psf_corners=True, psf_phase=True)
        changed = next(iter(other.values()))
        array = getattr(changed, spec.name)
        array.view(np.uint8).reshape(-1)[0] ^= 1
        assert not changed.equals(cell)
    # an optional plane may be absent (None), which equality tells from present
    without = make_patch(n_noise=3, psf_size=7)
    bare = next(iter(without.values()))
    assert bare.psf_corners is None
    assert bare.plane_names == cell_planes.required_plane_names()
    assert cell.plane_names == cell_planes.plane_names()
    optional = ["psf_corners", "psf_phase", "psf_maps"]
    assert [spec.name for spec in cell_planes.PLANES if spec.optional] == optional
    with_corners = copy.copy(bare)
    with_corners.psf_corners = np.stack([bare.psf] * 4)
    assert not with_corners.equals(bare) and not bare.equals(with_corners)


def test_unit_keywords_follow_the_unit_kinds():
    meta = make_patch(n_noise=1).metadata.model_copy(update={"units": "count", "zero_point": 27})
    cards = meta.unit_cards()
    for spec in cell_planes.PLANES:
        keys = {key: value for key, value, _ in cards.get(spec.name, [])}
        if spec.unit == "flux":
            assert keys == {"BUNIT": "count", "MAGZERO": 27.0}
        elif spec.unit == "flux_squared":
            assert keys == {"BUNIT": "count2", "MAGZERO": 27.0}
        elif spec.unit == "mask_bits":
            assert keys and all(key.startswith("MP_") for key in keys)
        else:
            assert keys == {}


@pytest.mark.parametrize("n_noise, corners", [(0, False), (2, False), (2, True)])
@pytest.mark.parametrize("compression", [None, "lossless"])
def test_fits_files_follow_the_description(tmp_path, n_noise, corners, compression):
    patch = make_patch(n_noise=n_noise, psf_size=5, psf_corners=corners, psf_phase=corners)
    path = tmp_path / "patch.fits"
    api.write(patch, path, compression=compression)
    stored = [
        spec
        for spec in cell_planes.PLANES
        if (n_noise or not spec.per_realization)  # no zero-size HDUs
        and (corners or not spec.optional)  # nor absent optional planes
    ]
    index = next(iter(patch))
    with fitsio.FITS(str(path)) as fits:
        table = fits["CELLINDEX"].read()
        columns = [name for name in table.dtype.names if name.startswith("HDU_")]
        assert columns == [f"HDU_{name.upper()}" for name in cell_planes.cell_objects()]
        row = table[(table["CELL_X"] == index[0]) & (table["CELL_Y"] == index[1])][0]
        numbers = [int(row[column]) for column in columns]
        expected = [numbers[0] + k for k in range(len(stored) + 1)]
        assert [n for n in numbers if n >= 0] == expected  # the description's order
        for spec in stored:
            hdu = fits[int(row[f"HDU_{spec.name.upper()}"])]
            header = hdu.read_header()
            assert header["PLANE"].strip() == spec.name
            assert hdu.get_extname() == fits_format.extname(index, spec.name)
            tile = header.get("ZCMPTYPE")
            wanted = _FITS_COMPRESSION[spec.compression] if compression else None
            assert (tile.strip() if tile else None) == wanted
            assert ("BUNIT" in header) == (spec.unit in ("flux", "flux_squared"))
        assert fits[int(row["HDU_INPUTS"])].read_header()["PLANE"].strip() == "inputs"
    assert api.read(path).equals(patch)
    assert [text.split(" ")[0] for text in patch_summary(str(path))["planes"]] == [
        *(spec.name for spec in stored),
        "inputs",
    ]


@pytest.mark.parametrize("corners", [False, True])
def test_hdf5_files_follow_the_description(tmp_path, corners):
    patch = make_patch(n_noise=2, psf_size=5, psf_corners=corners)
    path = tmp_path / "patch.h5"
    api.write(patch, path)
    held = next(iter(patch.values())).plane_names
    assert ("psf_corners" in held) == corners
    with h5py.File(path, "r") as h5:
        listed = json.loads(bytes(h5.attrs["contents"]))["planes"]
        assert listed == sorted((*held, cell_planes.INPUTS))
        group = h5["cells"][hdf5_format.group_name(next(iter(patch)))]
        assert list(group) == listed  # HDF5 lists names sorted
        shapes = expected_shapes(patch.metadata, next(iter(patch.values())).outer_bbox)
        for spec in cell_planes.PLANES:
            if spec.name not in held:
                continue
            dataset = group[spec.name]
            assert dataset.dtype == spec.stored_dtype
            assert dataset.shape == shapes[spec.name]
            assert bytes(dataset.attrs["plane"]) == spec.name.encode("ascii")
            assert ("BUNIT" in dataset.attrs) == (spec.unit in ("flux", "flux_squared"))
    assert api.read(path).equals(patch)


def test_size_estimate_bounds_the_files(tmp_path):
    patch = make_patch(n_noise=2)
    for name in ("patch.fits", "patch.h5"):
        api.write(patch, tmp_path / name)
        assert os.path.getsize(tmp_path / name) <= api._estimated_size(patch)


def test_a_plane_added_to_the_description_is_written(tmp_path, monkeypatch):
    """Adding a plane means adding it to the description: both writers, the cell-index
    columns, the stored shapes and the ``info`` listing pick it up."""
    weight = cell_planes.PlaneSpec(
        "weight",
        np.dtype(np.float32),
        per_realization=False,
        stamp=False,
        compression="float_bits",
        unit="fraction",
        doc="a plane that does not exist",
    )
    psf_spec = cell_planes.plane("psf")
    stamp = dataclasses.replace(
        weight, name="kernel", dtype=psf_spec.dtype, stamp=True, compression="none"
    )
    monkeypatch.setattr(cell_planes, "PLANES", (*cell_planes.PLANES, weight, stamp))
    patch = make_patch(n_noise=1, psf_size=5, psf_corners=True, psf_phase=True)
    rng = np.random.default_rng(1)
    for cell in patch.values():  # the model has no such attributes: given by hand here
        cell.weight = rng.standard_normal(cell.shape, dtype=np.float32)  # type: ignore[attr-defined]
        cell.kernel = rng.standard_normal((5, 5))  # type: ignore[attr-defined]
    index, cell = next(iter(patch.items()))
    shapes = expected_shapes(patch.metadata, cell.outer_bbox)
    assert shapes["weight"] == cell.shape and shapes["kernel"] == (5, 5)
    assert stored_planes(patch.metadata)[-3:] == ["weight", "kernel (5x5)", "inputs"]
    assert api._estimated_size(patch) > sum(
        getattr(cell, name).nbytes for c in patch.values() for name in ("weight", "kernel")
    )

    for compression in (None, "lossless"):
        path = tmp_path / f"patch-{compression}.fits"
        api.write(patch, path, compression=compression)
        with fitsio.FITS(str(path)) as fits:
            row = fits["CELLINDEX"].read()[0]
            assert (int(row["CELL_X"]), int(row["CELL_Y"])) == index
            for name in ("weight", "kernel"):
                hdu = fits[int(row[f"HDU_{name.upper()}"])]
                assert hdu.get_extname() == fits_format.extname(index, name)
                data = hdu.read()  # compressed floats decode to the floats themselves
                assert data.dtype.kind == "f"
                np.testing.assert_array_equal(data, getattr(cell, name))
            assert int(row["HDU_INPUTS"]) == int(row["HDU_KERNEL"]) + 1

    path = tmp_path / "patch.h5"
    api.write(patch, path)
    with h5py.File(path, "r") as h5:
        group = h5["cells"][hdf5_format.group_name(index)]
        assert set(group) == set(cell_planes.cell_objects())
        np.testing.assert_array_equal(group["weight"][()], cell.weight)  # type: ignore[attr-defined]
        np.testing.assert_array_equal(group["kernel"][()], cell.kernel)  # type: ignore[attr-defined]


def test_format_document_lists_the_planes():
    """The plane table of ``docs/format.md`` names the described planes, in order, with
    their dtypes."""
    text = (Path(__file__).parents[1] / "docs" / "format.md").read_text()
    table = text.split("### Planes of a cell", 1)[1].split("\n\n", 2)[1]
    rows = [line.split("|")[1:3] for line in table.splitlines()[2:]]
    assert [(name.strip().strip("`"), dtype.strip()) for name, dtype in rows] == [
        (spec.name, spec.dtype.name) for spec in cell_planes.PLANES
    ]
