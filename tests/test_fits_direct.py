"""The direct FITS writer gives the bytes CFITSIO (through fitsio) gives, card by card and file
by file, and falls back to CFITSIO for what it does not reproduce."""

from __future__ import annotations

import hashlib

import fitsio
import numpy as np
import pytest
from coadd_factory import make_patch

from cellcoadd.io import api
from cellcoadd.io._fits import direct as fits_direct
from cellcoadd.io._fits.checksums import stabilise_fits_checksums
from cellcoadd.io.coadd import fits_format

_VALUES = [
    0,
    -7,
    123456789012,
    True,
    False,
    0.0,
    -0.0,
    1.0,
    -30.0,
    500.5,
    -5.5555555555556e-05,
    1e-300,
    -1.2345678901234567e100,
    1 / 3,
    123456789.123456789,
    1e15,
    1e16,
    "",
    "a",
    "nJy",
    "it's",
    "RA---TAN",
    "x" * 60,
]


def _header_cards(path) -> list[bytes]:
    raw = path.read_bytes()
    end = raw.index(b"END" + b" " * 77, 2880)
    return [raw[i : i + 80] for i in range(2880, end, 80)]


@pytest.mark.parametrize("comment", ["", "a comment", "c" * 40])
@pytest.mark.parametrize("name", ["KEY", "LONGKEY8", "MP_NO_DATA"])
def test_cards_match_cfitsio(tmp_path, name, comment):
    path = tmp_path / "cards.fits"
    expected: list[tuple[object, bytes | None]] = []
    with fitsio.FITS(str(path), "rw", clobber=True) as fits:
        fits.write(np.zeros((2, 2), dtype=np.float32))
        for number, value in enumerate(_VALUES):
            key = f"{name[:6]}{number:02d}" if len(name) <= 8 else f"{name}{number:02d}"
            try:
                mine: bytes | None = fits_direct.card(key, value, comment)
            except fits_direct.UnsupportedCard:
                mine = None
            fits[0].write_key(key, value, comment=comment)
            expected.append((value, mine))
    cards = _header_cards_primary(path)
    written = [card for card in cards if card[:8] not in (b"SIMPLE  ", b"BITPIX  ", b"NAXIS   ")]
    written = [card for card in written if not card.startswith((b"NAXIS", b"EXTEND", b"COMMENT"))]
    mine_cards = [mine for _, mine in expected]
    # every card the direct writer formats is the card CFITSIO writes
    position = 0
    for value, mine in zip(_VALUES, mine_cards, strict=True):
        cfitsio_card = written[position]
        position += 1
        while position < len(written) and written[position].startswith(b"CONTINUE"):
            position += 1
        if mine is not None:
            assert mine == cfitsio_card, (value, mine, cfitsio_card)
    if len(name) <= 8 and len(comment) < 30:
        assert all(mine is not None for mine in mine_cards[:-1])


def _header_cards_primary(path) -> list[bytes]:
    raw = path.read_bytes()
    cards = []
    for start in range(0, len(raw), 80):
        card = raw[start : start + 80]
        if card.startswith(b"END "):
            break
        cards.append(card)
    return cards


def _classic(patch, path):
    cells = list(patch.cells.values())
    fits_format._write_fits(
        patch.metadata, cells, iter(cells), str(path), compress=False, direct=False,
        present=cells[0].plane_names,
    )  # fmt: skip
    stabilise_fits_checksums(path)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"n_noise": 0},
        {"n_noise": 2, "band": "\u00e9\u03c0"},
        {"n_noise": 3, "psf_size": 7, "empty": ((1, 1),)},
        {"n_noise": 1, "psf_corners": True, "psf_phase": True, "empty": ((0, 1), (2, 2))},
    ],
)
def test_direct_file_identical_to_cfitsio(tmp_path, kwargs):
    patch = make_patch(seed=4, **kwargs)
    direct, classic = tmp_path / "direct.fits", tmp_path / "classic.fits"
    api.write(patch, direct)
    _classic(patch, classic)
    assert (
        hashlib.sha256(direct.read_bytes()).digest()
        == hashlib.sha256(classic.read_bytes()).digest()
    )
    assert api.read(direct).equals(patch)


def test_big_endian_planes_written_as_native(tmp_path):
    patch = make_patch(seed=5)
    index = next(iter(patch.cells))
    cell = patch.cells[index]
    cell.image = cell.image.byteswap().view(cell.image.dtype.newbyteorder())
    assert not cell.image.dtype.isnative
    direct, classic = tmp_path / "direct.fits", tmp_path / "classic.fits"
    api.write(patch, direct)
    _classic(patch, classic)
    assert direct.read_bytes() == classic.read_bytes()


def test_unsupported_cards_fall_back_to_cfitsio(tmp_path, monkeypatch):
    patch = make_patch(seed=6)
    calls = []

    def refuse(*args, **kwargs):
        calls.append(1)
        raise fits_direct.UnsupportedCard("not today")

    monkeypatch.setattr(fits_direct, "image_header", refuse)
    path = tmp_path / "fallback.fits"
    api.write(patch, path)
    assert calls
    classic = tmp_path / "classic.fits"
    _classic(patch, classic)
    assert path.read_bytes() == classic.read_bytes()
    assert api.read(path).equals(patch)


def test_card_refusals():
    for name, value in [("BITPIX", 8), ("KEY", float("nan")), ("KEY", None), ("K Y", 1)]:
        with pytest.raises(fits_direct.UnsupportedCard):
            fits_direct.check_keys([{"name": name, "value": value}])
    with pytest.raises(fits_direct.UnsupportedCard):
        fits_direct.card("LONGNAMEKEY", "text")
