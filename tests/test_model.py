"""The in-memory data model: InputRecord, CellCoadd, PatchMetadata, PatchCoadd."""

from __future__ import annotations

import json

import numpy as np
import pytest
from astropy.wcs import WCS, Sip
from pydantic import ValidationError

from cellcoadd.errors import CellCoaddError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.inputs import INPUT_STATUSES, REJECTION_REASONS, InputRecord
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.patch_coadd import FORMAT_VERSION, PatchCoadd, PatchMetadata
from cellcoadd.model.wcs_codec import wcs_from_record, wcs_to_record

CONFIG = SkyMapConfig(
    cell_inner=6, cell_border=2, cells_per_patch=3, patch_border_cells=1, patches_per_tract=2
)
NO_DATA = MaskBits().value("NO_DATA")


def record(**changes) -> InputRecord:
    fields = {
        "visit": 1,
        "detector": 2,
        "band": "r",
        "weight": 1.0,
        "status": "used",
        "overlap_fraction": 1.0,
        "psf_fwhm": 0.8,
        "psf_e1": 0.0,
        "psf_e2": 0.01,
        "psf_T": 0.4,
        "zero_point": 30.0,
    }
    fields.update(changes)
    return InputRecord(**fields)


def metadata(**changes) -> PatchMetadata:
    fields = {
        "skymap_config": CONFIG,
        "tract": 4,
        "tract_center": (10.0, -30.0),
        "patch": (1, 0),
        "band": "i",
        "units": "nJy",
        "build_config": BuildConfig(n_noise=2, psf_size=3),
    }
    fields.update(changes)
    return PatchMetadata(**fields)


def simple_wcs(x_start: int = 0, y_start: int = 0) -> WCS:
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = [10.0, -30.0]
    wcs.wcs.crpix = [12.5 - x_start, 12.5 - y_start]
    wcs.wcs.cd = [[-0.2 / 3600, 0.0], [0.0, 0.2 / 3600]]
    return wcs


def cell_args(meta: PatchMetadata, index: tuple[int, int], seed: int = 0) -> dict:
    """Keyword arguments of a valid non-empty cell; planes encode (cx, cy) for stitch checks."""
    rng = np.random.default_rng(seed)
    inner, outer = meta.cell_boxes(index)
    shape = outer.shape
    psf = rng.uniform(size=(meta.psf_size, meta.psf_size))
    return {
        "image": rng.standard_normal(shape).astype(np.float32) + 100 * index[0] + index[1],
        "mask": rng.integers(0, 8, size=shape, dtype=np.int32),
        "variance": rng.uniform(1, 2, size=shape).astype(np.float32),
        "noise": rng.standard_normal((meta.n_noise, *shape)).astype(np.float32),
        "mfrac": rng.uniform(0, 0.1, size=shape).astype(np.float32),
        "psf": psf / psf.sum(),
        "inputs": [record(visit=1), record(visit=2, weight=0.0, status="edge")],
        "tract": meta.tract,
        "index": index,
        "inner_bbox": inner,
        "outer_bbox": outer,
        "wcs": simple_wcs(outer.x_start, outer.y_start),
    }


# ------------------------------------------------------------------------------ InputRecord


def test_input_record_rules():
    assert INPUT_STATUSES[0] == "used" and "edge" in REJECTION_REASONS
    assert record().is_used and record().key == (1, 2)
    with pytest.raises(ValidationError, match="positive weight"):
        record(weight=0.0)
    with pytest.raises(ValidationError, match="weight 0"):
        record(status="edge", weight=0.5)
    with pytest.raises(ValidationError):
        record(weight=float("nan"))
    with pytest.raises(ValidationError):
        record(status="cosmic_bad_luck", weight=0.0)
    with pytest.raises(ValidationError):
        record(overlap_fraction=1.5)
    for band in ("", " r", "r\n", "a\x00b"):
        with pytest.raises(ValidationError, match="band"):
            record(band=band)
    assert record(band="y\u00b2").band == "y\u00b2"
    with pytest.raises(ValidationError):
        record().visit = 5  # frozen


def test_input_record_identical_compares_bits():
    nan = record(psf_T=float("nan"), psf_fwhm=float("nan"))
    assert nan != record(psf_T=float("nan"), psf_fwhm=float("nan"))  # plain NaN semantics
    assert nan.identical(record(psf_T=float("nan"), psf_fwhm=float("nan")))
    assert not record(psf_e1=0.0).identical(record(psf_e1=-0.0))
    assert not record().identical(record(zero_point=30.000000000000004))
    round_tripped = InputRecord.model_validate_json(nan.model_dump_json())
    assert round_tripped.identical(nan)


# -------------------------------------------------------------------------------- CellCoadd


def test_cell_accepts_and_converts():
    meta = metadata()
    args = cell_args(meta, (3, 0))
    args["image"] = args["image"].astype(np.float64)
    args["variance"] = args["variance"].astype(">f4")  # big-endian: converted bit-exactly
    args["mask"] = args["mask"].astype(np.uint8)
    args["psf"] = args["psf"].astype(np.float32)
    args["psf"] = args["psf"] / args["psf"].sum(dtype=np.float64)
    cell = CellCoadd(**args)
    assert cell.image.dtype == np.float32 and cell.mask.dtype == np.int32
    assert cell.psf.dtype == np.float64 and cell.variance.dtype == np.float32
    assert cell.variance.tobytes() == args["variance"].astype("<f4").tobytes()
    assert (cell.n_used, cell.n_noise, cell.is_empty) == (1, 2, False)
    assert cell.shape == (10, 10)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("image", np.zeros((10, 9), np.float32), r"image must have the outer-box shape \(10, 10\)"),
        ("image", np.zeros((10, 10), np.int32), "image must be a float array"),
        ("mask", np.zeros((10, 10), np.float32), "mask must be an integer array"),
        ("mask", np.full((10, 10), 2**40), "int32"),
        ("variance", np.zeros((1, 10, 10), np.float32), "variance must have the outer-box shape"),
        ("noise", np.zeros((10, 10), np.float32), r"noise must have shape \(K, 10, 10\)"),
        ("noise", np.zeros((2, 10, 11), np.float32), "noise must have shape"),
        ("psf", np.full((4, 4), 1 / 16), "odd square"),
        ("psf", np.full((3, 5), 1 / 15), "odd square"),
        ("psf", np.full((3, 3), 0.2), "sum to 1"),
        ("index", (1, 2, 3), "pair"),
        ("tract", 1.5, "tract must be an integer"),
        ("inner_bbox", Box(x_start=0, x_stop=20, y_start=0, y_stop=6), "not inside"),
        ("wcs", "not a wcs", "celestial"),
        ("inputs", [record(), record()], "more than once"),
        ("inputs", [{"visit": 1}], "invalid input record"),
    ],
)
def test_cell_refuses_malformed_fields(field, value, message):
    args = cell_args(metadata(), (3, 0))
    args[field] = value
    with pytest.raises(CellCoaddError, match=message):
        CellCoadd(**args)


def test_empty_cell():
    meta = metadata()
    inner, outer = meta.cell_boxes((2, 1))
    rejected = [record(status="edge", weight=0.0)]
    cell = CellCoadd.empty(
        tract=4,
        index=(2, 1),
        inner_bbox=inner,
        outer_bbox=outer,
        wcs=simple_wcs(),
        n_noise=2,
        psf_size=3,
        inputs=rejected,
    )
    assert cell.is_empty and cell.n_used == 0 and cell.inputs == rejected
    assert np.isnan(cell.image).all() and np.isnan(cell.psf).all()
    assert (cell.mask == NO_DATA).all() and cell.noise.shape == (2, 10, 10)
    args = cell_args(meta, (2, 1))
    args["inputs"] = rejected
    with pytest.raises(CellCoaddError, match="NaN image"):
        CellCoadd(**args)


def test_inner_gives_views_of_the_inner_box():
    meta = metadata()
    cell = CellCoadd(**cell_args(meta, (-1, 0)))  # negative index: border cell at tract edge
    assert cell.outer_bbox.x_start == -8
    inner = cell.inner
    assert inner.image.shape == (6, 6) and inner.noise.shape == (2, 6, 6)
    np.testing.assert_array_equal(inner.image, cell.image[2:8, 2:8])
    for name in ("image", "mask", "variance", "noise", "mfrac"):
        assert np.shares_memory(getattr(inner, name), getattr(cell, name))
    inner.image[0, 0] = 42.0
    assert cell.image[2, 2] == 42.0


def test_equals_is_bit_exact():
    meta = metadata()
    args = cell_args(meta, (3, 1))
    cell = CellCoadd(**args)
    assert cell.equals(CellCoadd(**args)) and cell == CellCoadd(**args)

    def changed(mutate):
        copy = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in args.items()}
        mutate(copy)
        return CellCoadd(**copy)

    def flip_bit(c):
        c["image"].view(np.uint32)[0, 0] ^= 1

    def nan_payload(c):
        c["variance"][1, 1] = np.nan
        c["variance"].view(np.uint32)[1, 1] |= 5

    def negative_zero(c):
        c["mfrac"][2, 2] = -0.0

    def more_inputs(c):
        c["inputs"] = [*c["inputs"], record(visit=9)]

    def other_wcs(c):
        c["wcs"] = c["wcs"].deepcopy()
        c["wcs"].wcs.crpix = [c["wcs"].wcs.crpix[0] + 1e-12, c["wcs"].wcs.crpix[1]]

    def other_mask(c):
        c["mask"][0, 0] ^= 1

    args["mfrac"][2, 2] = 0.0
    args["variance"][1, 1] = np.nan
    cell = CellCoadd(**args)
    for mutate in (flip_bit, nan_payload, negative_zero, more_inputs, other_wcs, other_mask):
        assert not cell.equals(changed(mutate)), mutate.__name__
    assert not cell.equals("a string")


def test_wcs_record_is_exact_and_json_safe():
    wcs = simple_wcs()
    wcs.wcs.crval = [150.123456789012345, -2.345678901234567]
    wcs.wcs.crpix = [1234.567890123456789, -77.12345678901234]
    wcs.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"]
    a = np.zeros((3, 3))
    a[2, 0] = 1.234567890123456e-7
    b = np.zeros((3, 3))
    b[0, 2] = -3.3333333333333e-7
    wcs.sip = Sip(a, b, None, None, wcs.wcs.crpix)
    record_ = wcs_to_record(wcs)
    rebuilt = wcs_from_record(json.loads(json.dumps(record_)))
    assert wcs_to_record(rebuilt) == record_
    np.testing.assert_array_equal(rebuilt.wcs.crval, wcs.wcs.crval)
    np.testing.assert_array_equal(rebuilt.wcs.crpix, wcs.wcs.crpix)
    np.testing.assert_array_equal(rebuilt.sip.a, wcs.sip.a)
    pixels = np.random.default_rng(0).uniform(-50, 3000, size=(50, 2))
    np.testing.assert_array_equal(rebuilt.all_pix2world(pixels, 0), wcs.all_pix2world(pixels, 0))


# ----------------------------------------------------------------------------- PatchMetadata


def test_patch_metadata_validation_and_derived_values():
    meta = metadata()
    assert meta.format_version == FORMAT_VERSION and meta.format_major == 1
    assert (meta.n_noise, meta.psf_size) == (2, 3)
    assert (meta.cell_inner, meta.cell_border, meta.cell_outer) == (6, 2, 10)
    assert meta.inner_cell_indices == [(cx, cy) for cy in range(0, 3) for cx in range(3, 6)]
    assert len(meta.all_cell_indices) == 25 and (2, -1) in meta.all_cell_indices
    assert meta.patch_inner_bbox == Box(x_start=18, x_stop=36, y_start=0, y_stop=18)
    assert PatchMetadata.model_validate_json(meta.model_dump_json()) == meta
    unicode_band = metadata(band="y\u00b2")
    assert PatchMetadata.model_validate_json(unicode_band.model_dump_json()) == unicode_band
    for bad in (
        {"patch": (2, 0)},
        {"tract_center": (360.0, 0.0)},
        {"tract_center": (0.0, float("nan"))},
        {"band": " i"},
        {"format_version": "1"},
        {"units": ""},
        {"mask_bits": MaskBits(bits={"BAD": 0})},
        {"surprise": 1},
    ):
        with pytest.raises(ValidationError):
            metadata(**bad)


# ------------------------------------------------------------------------------- PatchCoadd


def full_patch(meta: PatchMetadata, skip=(), empty=()) -> PatchCoadd:
    cells = {}
    for n, index in enumerate(meta.all_cell_indices):
        if index in skip:
            continue
        if index in empty:
            inner, outer = meta.cell_boxes(index)
            cells[index] = CellCoadd.empty(
                tract=meta.tract,
                index=index,
                inner_bbox=inner,
                outer_bbox=outer,
                wcs=simple_wcs(outer.x_start, outer.y_start),
                n_noise=meta.n_noise,
                psf_size=meta.psf_size,
            )
        else:
            cells[index] = CellCoadd(**cell_args(meta, index, seed=n))
    return PatchCoadd(meta, cells)


def test_patch_mapping_access():
    meta = metadata()
    patch = full_patch(meta, skip=[(2, -1)], empty=[(4, 1)])
    assert len(patch) == 24 and (2, -1) not in patch and (3, 0) in patch
    assert patch[3, 0].index == (3, 0)
    assert list(patch) == sorted(patch.cells)
    assert patch.empty_cell_indices == [(4, 1)]
    assert patch.inner_cell_indices == meta.inner_cell_indices
    assert patch == full_patch(meta, skip=[(2, -1)], empty=[(4, 1)])
    assert patch != full_patch(meta, empty=[(4, 1)])


def test_stitch_matches_manual_assembly():
    meta = metadata()
    patch = full_patch(meta, skip=[(5, 2)], empty=[(4, 1)])
    side = meta.cell_inner
    for plane, noise_index in (
        ("image", None),
        ("variance", None),
        ("mfrac", None),
        ("mask", None),
        ("noise", 1),
    ):
        stitched = patch.stitch(plane, noise_index=noise_index)
        assert stitched.shape == (18, 18)
        for cx, cy in meta.inner_cell_indices:
            block = stitched[cy * side : (cy + 1) * side, (cx - 3) * side : (cx - 2) * side]
            if (cx, cy) in ((5, 2), (4, 1)):
                if plane == "mask":
                    assert (block == NO_DATA).all()
                else:
                    assert np.isnan(block).all()
                continue
            views = patch[cx, cy].inner
            expected = views.noise[1] if plane == "noise" else getattr(views, plane)
            np.testing.assert_array_equal(block, expected)
    image = patch.stitch()
    # Rows/columns follow tract pixels: the cell at (cx, cy) sits at its own offset.
    assert abs(image[0, 0] - 300) < 10 and abs(image[side, 2 * side] - 501) < 10
    with pytest.raises(ValueError, match="noise_index"):
        patch.stitch("noise")
    with pytest.raises(ValueError, match="noise_index"):
        patch.stitch("image", noise_index=0)
    with pytest.raises(ValueError, match="unknown plane"):
        patch.stitch("psf")


def test_patch_refuses_inconsistent_cells():
    meta = metadata()
    good = cell_args(meta, (3, 0))

    def attempt(key, **changes):
        args = {**good, **changes}
        return PatchCoadd(meta, {key: CellCoadd(**args)})

    with pytest.raises(CellCoaddError, match="stored under"):
        attempt((4, 0))
    with pytest.raises(CellCoaddError, match="tract"):
        attempt((3, 0), tract=5)
    # a cell beyond the tract: its boxes follow the same grid
    side = meta.cell_inner
    far_inner = Box(x_start=9 * side, x_stop=10 * side, y_start=0, y_stop=side)
    far_outer = far_inner.grow(meta.cell_border)
    with pytest.raises(CellCoaddError, match="not an inner or border cell"):
        attempt((9, 0), index=(9, 0), inner_bbox=far_inner, outer_bbox=far_outer)
    shifted = good["outer_bbox"].shifted(1, 0)
    with pytest.raises(CellCoaddError, match="boxes"):
        attempt((3, 0), outer_bbox=shifted, inner_bbox=good["inner_bbox"].shifted(1, 0))
    with pytest.raises(CellCoaddError, match="noise realizations"):
        attempt((3, 0), noise=np.zeros((1, 10, 10), np.float32))
    psf5 = np.full((5, 5), 1 / 25)
    with pytest.raises(CellCoaddError, match="PSF stamp"):
        attempt((3, 0), psf=psf5)
    with pytest.raises(CellCoaddError, match="no name"):
        attempt((3, 0), mask=np.full((10, 10), 1 << 20, np.int32))
    rejected = [record(status="edge", weight=0.0)]
    with pytest.raises(CellCoaddError, match="NO_DATA"):
        attempt((3, 0), inputs=rejected, image=np.full((10, 10), np.nan, np.float32))
    with pytest.raises(TypeError):
        PatchCoadd({"not": "metadata"}, {})
