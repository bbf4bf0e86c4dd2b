"""Optional planes survive every route: a built cell's parcel (how it travels back from a
worker process) is derived from the plane description, and a patch refuses cells that
disagree with the planes its build declares. The builds over any number of workers with
every optional plane on are in test_build.py, test_executors.py and test_survey_run.py."""

from __future__ import annotations

import copy
import inspect
import pickle

import numpy as np
import pytest
from coadd_factory import make_patch

from cellcoadd.builder.patch import _parcel, parcel_fields
from cellcoadd.errors import InvalidCoaddError
from cellcoadd.model import planes as cell_planes
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.patch_coadd import PatchCoadd


def test_a_parcel_carries_every_plane_and_field_of_a_cell():
    patch = make_patch(n_noise=1, psf_size=5, psf_corners=True)
    arguments = set(inspect.signature(CellCoadd).parameters) - {"wcs", "common"}
    assert set(cell_planes.plane_names()) <= set(parcel_fields())
    assert arguments <= set(parcel_fields())
    assert cell_planes.plane("psf_corners").optional
    for cell in patch.values():
        parcel = pickle.loads(pickle.dumps(_parcel(cell), protocol=5))  # as between processes
        assert parcel["psf_corners"] is not None
        assert CellCoadd(**parcel, wcs=cell.wcs).equals(cell), cell.index


def test_a_plane_added_to_the_description_travels_in_the_parcel(monkeypatch):
    weight = cell_planes.PlaneSpec(
        "weight",
        np.dtype(np.float32),
        per_realization=False,
        stamp=False,
        compression="float_bits",
        unit="fraction",
        doc="a plane that does not exist",
        optional=True,
        config_flag="weight",
    )
    cell = next(iter(make_patch(n_noise=1, psf_size=5).values()))
    monkeypatch.setattr(cell_planes, "PLANES", (*cell_planes.PLANES, weight))
    assert cell_planes.optional_plane_flags()["weight"] == "weight"
    cell.weight = np.ones(cell.shape, dtype=np.float32)  # type: ignore[attr-defined]
    assert _parcel(cell)["weight"] is cell.weight  # type: ignore[attr-defined]


def _without_corners(cell: CellCoadd) -> CellCoadd:
    bare = copy.copy(cell)
    bare.psf_corners = None
    return bare


def test_a_patch_refuses_cells_that_disagree_with_its_declared_planes():
    with_corners = make_patch(n_noise=1, psf_size=5, psf_corners=True)
    first, *rest = with_corners.cells
    # every cell without them, as a build whose parcels dropped them: refused, not written
    # as a patch that says psf_corners but holds none
    bare = {index: _without_corners(cell) for index, cell in with_corners.items()}
    with pytest.raises(InvalidCoaddError, match="lacks the plane 'psf_corners'") as info:
        PatchCoadd(with_corners.metadata, bare)
    assert info.value.cell == first and info.value.value == "psf_corners"
    assert "psf_corners" in info.value.allowed
    # one cell without them
    mixed = dict(with_corners.cells)
    mixed[rest[-1]] = _without_corners(mixed[rest[-1]])
    with pytest.raises(InvalidCoaddError, match="lacks the plane") as info:
        PatchCoadd(with_corners.metadata, mixed)
    assert info.value.cell == rest[-1]
    # cells with them in a patch whose build did not ask for them
    plain = make_patch(n_noise=1, psf_size=5)
    with pytest.raises(InvalidCoaddError, match="has the plane 'psf_corners'") as info:
        PatchCoadd(plain.metadata, dict(with_corners.cells))
    assert info.value.cell == first and "psf_corners" not in info.value.allowed
    # as declared: accepted
    assert PatchCoadd(with_corners.metadata, dict(with_corners.cells)).has_psf_corners
    assert not PatchCoadd(plain.metadata, dict(plain.cells)).has_psf_corners
