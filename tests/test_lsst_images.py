"""Conversion to and from lsst-images (the ``lsst`` extra, Python >= 3.12).

Skipped with a message where lsst-images cannot be imported; with ``CI`` set, a missing
lsst-images on Python >= 3.12 fails instead (``make test-lsst`` runs this file there).
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest
from coadd_factory import make_patch

try:
    import lsst.images
    import lsst.images.cells
except ImportError as err:
    if os.environ.get("CI") and sys.version_info >= (3, 12):
        raise ImportError(f"CI must run the lsst-images tests, but it is missing: {err}") from err
    pytest.skip(
        "lsst-images is not importable (needs Python >= 3.12 and the 'lsst' extra; "
        "`make test-lsst` runs these tests in .venv-lsst)",
        allow_module_level=True,
    )

import cellcoadd
from cellcoadd.errors import CellCoaddFormatError, InvalidCoaddError
from cellcoadd.io.foreign.lsst_images import from_lsst_images, to_lsst_images
from cellcoadd.model.patch_coadd import PatchCoadd, PatchMetadata

PLANES = ("image", "mask", "variance", "mfrac")


def counts_patch(patch: PatchCoadd, zero_point: float = 30.0) -> PatchCoadd:
    dump = patch.metadata.model_dump()
    dump.update(units="count", zero_point=zero_point)
    dump["build_config"].update(units="count", zero_point=zero_point)
    return PatchCoadd(PatchMetadata.model_validate(dump), patch.cells)


@pytest.fixture(scope="module")
def patch() -> PatchCoadd:
    # arbitrary float bits (NaN payloads, -0.0), an empty and a missing inner cell
    return make_patch(seed=3, empty=((2, 3),), missing=((3, 3),))


def assert_stitched_equal(read: PatchCoadd, expected: PatchCoadd) -> None:
    for plane in PLANES:
        assert read.stitch(plane).tobytes() == expected.stitch(plane).tobytes(), plane
    for k in range(expected.metadata.n_noise):
        assert read.stitch("noise", k).tobytes() == expected.stitch("noise", k).tobytes()


def test_public_exports() -> None:
    assert cellcoadd.to_lsst_images is to_lsst_images
    assert cellcoadd.from_lsst_images is from_lsst_images


@pytest.mark.parametrize("counts", [False, True], ids=["nJy", "count"])
def test_per_cell_round_trip_is_exact(patch: PatchCoadd, counts: bool) -> None:
    patch = counts_patch(patch) if counts else patch
    coadds = to_lsst_images(patch, mode="per_cell")
    assert set(coadds) == set(patch.cells)
    cell = patch[2, 2]
    one = coadds[2, 2]
    assert isinstance(one, lsst.images.cells.CellCoadd)
    assert str(one.unit) == ("ct" if counts else "nJy")
    assert one.bbox.x.start == cell.outer_bbox.x_start and one.bbox.y.stop == cell.outer_bbox.y_stop
    # Rubin's plane names at our bit numbers: SAT is SATURATED, CR COSMIC_RAY, ...
    rubin = {"SAT": "SATURATED", "CR": "COSMIC_RAY", "INTRP": "INTERPOLATED"}
    rubin["EDGE"] = "SENSOR_EDGE"
    bits = patch.metadata.mask_bits.bits
    assert set(one.mask.schema.names) == {rubin.get(name, name) for name in bits}
    for name, bit in bits.items():
        assert one.mask.schema.bit(rubin.get(name, name)) == one.mask.schema.bit(
            one.mask.schema[bit].name
        )
        assert np.array_equal(one.mask.get(rubin.get(name, name)), (cell.mask >> bit) & 1 != 0)
    assert one.mask.schema.descriptions["NO_DATA"]
    assert one.mask.get("SATURATED").shape == cell.mask.shape
    assert len(one.noise_realizations) == patch.metadata.n_noise
    used = [r for r in cell.inputs if r.is_used]
    contributions = one.provenance.contributions
    assert sorted(contributions["visit"]) == sorted(r.visit for r in used)
    weights = {int(row["visit"]): float(row["weight"]) for row in contributions}
    assert weights == {r.visit: r.weight for r in used}
    back = from_lsst_images(coadds)
    assert back.metadata == patch.metadata
    assert list(back.cells) == list(patch.cells)
    for index, expected in patch.cells.items():
        assert back[index].equals(expected), index  # pixels, noise, mask, mfrac, PSF, inputs


def test_stitched_equals_patch_stitch(patch: PatchCoadd) -> None:
    coadd = to_lsst_images(patch)
    assert isinstance(coadd, lsst.images.cells.CellCoadd)
    box = patch.patch_inner_bbox
    assert (coadd.bbox.x.start, coadd.bbox.y.start) == (box.x_start, box.y_start)
    assert np.array_equal(coadd.image.array.view(np.uint32), patch.stitch("image").view(np.uint32))
    mfrac = coadd.mask_fractions["mfrac"].array
    assert mfrac.tobytes() == patch.stitch("mfrac").tobytes()
    no_data = coadd.mask.get("NO_DATA")
    assert np.array_equal(no_data, patch.stitch("mask") & 16 != 0)
    # the empty and the missing inner cells are marked missing, the others have a PSF
    assert len(coadd.psf.bounds.missing) == 2
    present = [i for i in patch.inner_cell_indices if i in patch and not patch[i].is_empty]
    grid = coadd.psf.bounds.grid
    side = patch.metadata.cell_inner
    for index in present:
        ij = lsst.images.cells.CellIJ(
            i=(index[1] * side - grid.bbox.y.start) // side,
            j=(index[0] * side - grid.bbox.x.start) // side,
        )
        assert np.array_equal(coadd.psf[ij].array, patch[index].psf)
    back = from_lsst_images(coadd)
    assert_stitched_equal(back, patch)
    assert back.metadata == patch.metadata
    assert (2, 3) in back and back[2, 3].is_empty and (3, 3) not in back
    for index in present:
        pairs = zip(back[index].inputs, patch[index].inputs, strict=True)
        assert all(a.identical(b) for a, b in pairs)
        assert np.isnan(back[index].image[0, 0])  # the border is not kept


@pytest.mark.parametrize("suffix", [".fits", ".sdf"])
@pytest.mark.parametrize("mode", ["stitched", "per_cell"])
def test_lsst_images_files(patch: PatchCoadd, tmp_path, suffix: str, mode: str) -> None:
    patch = counts_patch(patch) if suffix == ".sdf" else patch
    out = to_lsst_images(patch, mode=mode)
    coadd = out if mode == "stitched" else out[2, 2]
    path = tmp_path / f"coadd{suffix}"
    coadd.write(str(path))  # lsst-images' own writer
    read = lsst.images.cells.CellCoadd.read(str(path))  # and its own reader
    assert read.unit == coadd.unit
    for back in (from_lsst_images(read), from_lsst_images(path)):
        assert back.metadata == patch.metadata
        if mode == "per_cell":
            assert back[2, 2].equals(patch[2, 2])
        else:
            assert_stitched_equal(back, patch)


def test_suffixes_are_not_mixed(patch: PatchCoadd, tmp_path) -> None:
    ours = tmp_path / "ours.fits"
    cellcoadd.write(patch, ours)
    with pytest.raises(CellCoaddFormatError, match="cellcoadd.read"):
        from_lsst_images(ours)
    with pytest.raises(CellCoaddFormatError, match="Starlink NDF"):
        from_lsst_images(tmp_path / "coadd.h5")
    theirs = tmp_path / "theirs.fits"
    to_lsst_images(patch).write(str(theirs))
    with pytest.raises(CellCoaddFormatError):
        cellcoadd.read(theirs)


def test_refusals(patch: PatchCoadd) -> None:
    with pytest.raises(ValueError, match="mode"):
        to_lsst_images(patch, mode="tiles")  # type: ignore[arg-type]
    coadd = to_lsst_images(patch)
    del coadd.metadata["cellcoadd.format"]
    with pytest.raises(InvalidCoaddError, match="not written by cellcoadd"):
        from_lsst_images(coadd)
    other = make_patch(seed=4, patch=(0, 1))
    mixed = {**to_lsst_images(patch, "per_cell"), (9, 9): to_lsst_images(other, "per_cell")[0, 3]}
    with pytest.raises(InvalidCoaddError, match="different patches"):
        from_lsst_images(mixed)


def test_lsst_images_command_line_reads_our_export(patch: PatchCoadd, tmp_path) -> None:
    """lsst-images' own command line (it needs lsst-daf-butler, in the ``lsst`` extra)."""
    from click.testing import CliRunner
    from lsst.images.cli import main

    path = tmp_path / "coadd.fits"
    to_lsst_images(patch).write(str(path))
    result = CliRunner().invoke(main, ["inspect", str(path)])
    assert result.exit_code == 0, result.output
    assert "schema name:    cell_coadd" in result.output, result.output
    described = CliRunner().invoke(main, ["describe", str(path)])
    assert described.exit_code == 0, described.output
    assert "SATURATED" in described.output and "COSMIC_RAY" in described.output
