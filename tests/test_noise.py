"""The counter-based noise generator and the planes the builder warps."""

import numpy as np
import pytest
from scipy import special, stats

from cellcoadd.builder.kernels.accumulate import accumulate_warped
from cellcoadd.builder.kernels.input_planes import input_planes
from cellcoadd.builder.kernels.noise import ndtri, noise_key, philox4x32, standard_normal_field
from cellcoadd.geometry.box import Box

# Random123 tests/kat_vectors, "philox4x32 10": counter (4 words), key (2), result (4)
PHILOX_KNOWN_ANSWERS = [
    ((0, 0, 0, 0), (0, 0), (0x6627E8D5, 0xE169C58D, 0xBC57AC4C, 0x9B00DBD8)),
    (
        (0xFFFFFFFF,) * 4,
        (0xFFFFFFFF,) * 2,
        (0x408F276D, 0x41C83B0E, 0xA20BC7C6, 0x6D5451FD),
    ),
    (
        (0x243F6A88, 0x85A308D3, 0x13198A2E, 0x03707344),
        (0xA4093822, 0x299F31D0),
        (0xD16CFE09, 0x94FDCCEB, 0x5001E420, 0x24126EA1),
    ),
]
# The generator's base layer ends at this many sigma; beyond it the tail is inverted.
ZIGGURAT_TAIL_START = 3.6541528853610088


@pytest.mark.parametrize(("counter", "key", "expected"), PHILOX_KNOWN_ANSWERS)
def test_philox_matches_the_reference_vectors(counter, key, expected):
    words = philox4x32(*map(np.uint64, counter), *map(np.uint64, key))
    assert [int(w) for w in words] == list(expected)


def test_ndtri_is_the_inverse_normal_cdf_to_rounding():
    rng = np.random.default_rng(3)
    p = np.concatenate(
        [rng.random(20_000), np.logspace(-300, -1, 2000), 1 - np.logspace(-16, -1, 200)]
    )
    ours = np.array([ndtri(value) for value in p])
    reference = special.ndtri(p)
    np.testing.assert_allclose(ours, reference, rtol=5e-15, atol=1e-300)


@pytest.fixture(scope="module")
def normals():
    box = Box(x_start=0, x_stop=1000, y_start=0, y_stop=1000)
    return np.stack([standard_normal_field(7, 11, 3, r, box) for r in range(3)])


def test_noise_is_standard_normal(normals):
    sample = normals.ravel()
    n = sample.size
    assert abs(sample.mean()) < 5 / np.sqrt(n)
    assert abs(sample.var() - 1) < 5 * np.sqrt(2 / n)
    assert stats.kstest(sample, "norm").pvalue > 1e-4
    edges = np.linspace(-4.5, 4.5, 91)
    counts, _ = np.histogram(sample, edges)
    expected = n * np.diff(stats.norm.cdf(edges))
    chi2 = ((counts - expected) ** 2 / expected).sum()
    assert stats.chi2.sf(chi2, edges.size - 2) > 1e-4
    # the rare paths (wedges, and the tail beyond the base layer) have the right weight
    for threshold in (2.0, 3.0, ZIGGURAT_TAIL_START, 4.0):
        beyond = np.count_nonzero(np.abs(sample) > threshold)
        expected_beyond = n * 2 * stats.norm.sf(threshold)
        assert abs(beyond - expected_beyond) < 5 * np.sqrt(expected_beyond), threshold


def test_noise_is_uncorrelated_between_pixels_and_realizations(normals):
    n = normals[0].size
    limit = 5 / np.sqrt(n)
    for a, b in ((normals[0], normals[1]), (normals[1], normals[2]), (normals[0], normals[2])):
        assert abs(np.corrcoef(a.ravel(), b.ravel())[0, 1]) < limit
    field = normals[0]
    for shifted, base in ((field[:, 1:], field[:, :-1]), (field[1:], field[:-1])):
        assert abs(np.corrcoef(shifted.ravel(), base.ravel())[0, 1]) < limit
    other_visit = standard_normal_field(
        7, 12, 3, 0, Box(x_start=0, x_stop=1000, y_start=0, y_stop=1000)
    )
    assert abs(np.corrcoef(other_visit.ravel(), field.ravel())[0, 1]) < limit


def test_noise_depends_only_on_the_pixel_and_its_key():
    big = standard_normal_field(1, 2, 3, 1, Box(x_start=5, x_stop=305, y_start=40, y_stop=200))
    small = standard_normal_field(1, 2, 3, 1, Box(x_start=100, x_stop=131, y_start=77, y_stop=80))
    np.testing.assert_array_equal(small, big[77 - 40 : 80 - 40, 100 - 5 : 131 - 5])
    for other in ((2, 2, 3, 1), (1, 3, 3, 1), (1, 2, 4, 1), (1, 2, 3, 0)):
        field = standard_normal_field(*other, Box(x_start=100, x_stop=131, y_start=77, y_stop=80))
        assert not np.any(field == small)


def test_noise_keys_are_validated():
    with pytest.raises(ValueError, match="visit"):
        noise_key(0, -1, 0)
    with pytest.raises(ValueError, match="exposure grid"):
        standard_normal_field(0, 0, 0, 0, Box(x_start=-1, x_stop=3, y_start=0, y_stop=3))


def _rotated_positions(box: Box, shape=(40, 40), angle=0.6, scale=0.77):
    """Positions of a rotated, scaled output grid well inside ``box``."""
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    cos, sin = scale * np.cos(angle), scale * np.sin(angle)
    x = cos * (cols - shape[1] / 2) - sin * (rows - shape[0] / 2)
    y = sin * (cols - shape[1] / 2) + cos * (rows - shape[0] / 2)
    return x + (box.x_start + box.x_stop) / 2 + 0.13, y + (box.y_start + box.y_stop) / 2 + 0.41


def test_input_planes_fill_every_pixel_the_kernel_reads():
    box = Box(x_start=20, x_stop=80, y_start=30, y_stop=90)
    rng = np.random.default_rng(5)
    image = rng.normal(size=box.shape).astype(np.float32)
    variance = rng.uniform(0.5, 2.0, size=box.shape)
    bad = rng.random(box.shape) < 0.02
    x, y = _rotated_positions(box)
    args = (image, variance, bad, box)
    planes = input_planes(*args, x, y, 2.5, 3, (1, 2, 3))
    everywhere = np.meshgrid(
        np.arange(box.x_start, box.x_stop, dtype=float),
        np.arange(box.y_start, box.y_stop, dtype=float),
    )
    full = input_planes(*args, *everywhere, 2.5, 3, (1, 2, 3))
    assert np.count_nonzero(planes[..., 0]) < 0.8 * np.count_nonzero(full[..., 0])
    local_x, local_y = x - box.x_start, y - box.y_start
    warped = [
        accumulate_warped(
            p, local_x, local_y, np.zeros((p.shape[2], *x.shape)), np.ones(p.shape[2])
        )
        for p in (planes, full)
    ]
    np.testing.assert_array_equal(warped[0], warped[1])
    # what is filled: scaled image, noise with the pixel's sigma, scaled variance, bad mask
    filled = (planes[..., 4] > 0) & ~bad
    np.testing.assert_allclose(planes[..., 0][filled], 2.5 * image[filled])
    np.testing.assert_allclose(planes[..., 4][filled], 2.5**2 * variance[filled])
    unit = standard_normal_field(1, 2, 3, 2, box)
    np.testing.assert_allclose(
        planes[..., 3][filled], unit[filled] * np.sqrt(variance[filled]) * 2.5
    )
    read_bad = bad & (full[..., 5] > 0)
    assert np.all(full[..., :5][bad] == 0) and np.all(full[..., 5][bad] == 1)
    assert read_bad.any()


def test_input_planes_take_a_scalar_variance_and_no_mask_plane_without_bad_pixels():
    box = Box(x_start=0, x_stop=50, y_start=0, y_stop=50)
    x, y = _rotated_positions(box, shape=(30, 30))
    planes = input_planes(
        np.ones(box.shape), 4.0, np.zeros(box.shape, bool), box, x, y, 1.0, 2, (0, 1, 1)
    )
    assert planes.shape == (*box.shape, 4)  # image, 2 noise, variance: no mask plane
    read = planes[..., 3] > 0
    assert np.all(planes[..., 3][read] == 4.0)
    np.testing.assert_array_equal(
        planes[..., 1][read], 2.0 * standard_normal_field(0, 1, 1, 0, box)[read]
    )
