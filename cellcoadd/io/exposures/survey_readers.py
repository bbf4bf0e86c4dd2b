"""Survey single-epoch exposure files (LSST, DES, any multi-extension FITS layout) as
:class:`~cellcoadd.model.sources.ExposureSource` objects.

:class:`MefExposureFile` reads one detector exposure laid out as a :class:`MefLayout`
(:mod:`cellcoadd.io.exposures.mef_layout`): ``header()`` reads FITS headers only, ``load(box)``
reads only the pixels of ``box`` of each plane (fitsio slicing, tile-compressed HDUs
included), each once, and returns an :class:`~cellcoadd.model.exposure.Exposure` whose
``origin`` is the box's start and whose WCS is the file's WCS shifted to the cutout
(``CRPIX`` minus the offset: exact for TAN, TAN-SIP and TPV, whose distortions are
polynomials about ``CRPIX``). A source holds its paths, layout, options and PSF model
only; nothing stays open, so it pickles to worker processes.

Every problem with a file (missing file or HDU, shapes that differ between HDUs, no zero
point, an unnamed mask bit, unusable pixels) is a
:class:`~cellcoadd.errors.CellCoaddFormatError` naming the file and the HDU.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from typing import Any

import fitsio
import numpy as np
from astropy.io import fits
from astropy.wcs import WCS

from cellcoadd.errors import CellCoaddFormatError, CellCoaddTypeError, ExposureError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.wcs_utils import canonical_wcs, shifted_wcs
from cellcoadd.io._files.read_checks import is_file_failure
from cellcoadd.io._fits.wcs_header import WCS_KEYWORD
from cellcoadd.io.exposures.lsst_photocalib import photocalib_zero_point
from cellcoadd.io.exposures.mef_file import MefFile, open_mef
from cellcoadd.io.exposures.mef_layout import DES_LAYOUT, LSST_LAYOUT, MefLayout, zero_point_from
from cellcoadd.io.exposures.psf_files import read_psf_file
from cellcoadd.model.exposure import Exposure, PsfLike
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.sources import ExposureHeader, ExposureSource, cutout_box

PathLike = str | os.PathLike[str]


def psf_from(psf: PsfLike | PathLike, *, trust_psf: bool = False) -> PsfLike:
    """A PSF model from a path (PSFEx or Piff, by content; Piff only with ``trust_psf``,
    see :mod:`cellcoadd.io.exposures.psf_files`); other forms as given."""
    if not isinstance(psf, (str, os.PathLike)):
        return psf
    return read_psf_file(psf, trusted=trust_psf)


@dataclass(frozen=True, eq=False)
class _Meta:
    """What the headers of an exposure file say."""

    header: ExposureHeader
    image: int
    mask: int
    plane: int
    background: int | None


def _astropy_header(header: fitsio.FITSHDR, shape: tuple[int, int]) -> fits.Header:
    """The image's WCS cards as astropy sees them (:data:`WCS_KEYWORD`; compression
    keywords dropped)."""
    compressed = "ZIMAGE" in header
    cards = []
    for record in header.records():
        name = str(record.get("name") or "").upper()
        if (compressed and name.startswith("Z")) or not WCS_KEYWORD.fullmatch(name):
            continue
        try:
            cards.append(fits.Card.fromstring(record["card_string"]))
        except Exception as err:  # a card astropy cannot parse is not a WCS card: left out
            if not is_file_failure(err):
                raise
            continue
    out = fits.Header(cards)
    out["NAXIS"] = 2
    out["NAXIS1"] = shape[1]
    out["NAXIS2"] = shape[0]
    return out


#: Highest SIP polynomial order accepted: astropy allocates (order + 1)^2 coefficients
#: per polynomial (A_ORDER = 100000 asks for 75 GB); survey WCSs use at most ~9.
MAX_SIP_ORDER = 20


def _wcs(path: str, header: fits.Header, what: str) -> WCS:
    for key in ("A_ORDER", "B_ORDER", "AP_ORDER", "BP_ORDER"):
        if key in header:
            order = header[key]
            if isinstance(order, bool) or not isinstance(order, int):
                raise CellCoaddFormatError(path, f"{what}: {key} = {order!r} is not an integer")
            if not 0 <= order <= MAX_SIP_ORDER:
                raise CellCoaddFormatError(
                    path, f"{what}: {key} = {order} is outside 0..{MAX_SIP_ORDER}"
                )
    for key in header:
        # astropy raises AttributeError on a boolean CTYPE1 (found by the header fuzz); only
        # these cards' values are parsed here (another's may not parse: the WCS says so)
        if not key.startswith(("CTYPE", "CUNIT", "RADESYS")):
            continue
        try:
            value = header[key]
        except Exception as err:
            if not is_file_failure(err):
                raise
            raise CellCoaddFormatError(path, f"{what}: {key} cannot be parsed ({err})") from None
        if not isinstance(value, str):
            raise CellCoaddFormatError(path, f"{what}: {key} = {value!r} is not a string")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            wcs = WCS(header)
    except Exception as err:  # astropy raises several types for broken WCSs
        if not is_file_failure(err):
            raise
        raise CellCoaddFormatError(path, f"{what}: cannot parse the WCS ({err})") from None
    if not wcs.has_celestial or wcs.pixel_n_dim != 2:
        raise CellCoaddFormatError(path, f"{what}: no celestial 2-D WCS in the header")
    return wcs


class MefExposureFile(ExposureSource):
    """One detector exposure in a multi-extension FITS file of a known layout.

    Parameters
    ----------
    path : path-like
        The exposure file (``.fits`` or tile-compressed ``.fits.fz``).
    layout : MefLayout
        Where things are (:data:`~cellcoadd.io.exposures.mef_layout.LSST_LAYOUT`,
        :data:`~cellcoadd.io.exposures.mef_layout.DES_LAYOUT` or your own).
    psf : PsfModel, other PSF form of Exposure, or path
        The PSF model; a path is read now as a PSFEx or Piff model file, recognised by its
        content (:func:`cellcoadd.io.read_psf_file`): errors come early, and the parsed
        model travels with the source.
    zero_point : float, optional
        Used when no keyword of ``layout.zero_point_keys`` gives one.
    background : path-like, optional
        A background image file (its ``SCI`` HDU, else its first image HDU), subtracted.
    visit, detector : int, optional
        Identity, instead of the header's.
    band : str, optional
        Band, instead of the header's.
    trust_psf : bool
        Allow a ``psf`` path to be a Piff file, which holds pickled objects that run code
        when loaded: only for files you trust.
    """

    def __init__(
        self,
        path: PathLike,
        layout: MefLayout,
        psf: PsfLike | PathLike,
        *,
        zero_point: float | None = None,
        background: PathLike | None = None,
        visit: int | None = None,
        detector: int | None = None,
        band: str | None = None,
        trust_psf: bool = False,
    ):
        if not isinstance(layout, MefLayout):
            raise CellCoaddTypeError(
                f"layout must be a MefLayout, got {layout!r}", allowed=MefLayout
            )
        self.path = os.fspath(path)
        self.layout = layout
        self.psf = psf_from(psf, trust_psf=trust_psf)
        self.zero_point = zero_point
        self.background = os.fspath(background) if background is not None else None
        self.visit = visit
        self.detector = detector
        self.band = band

    def __repr__(self) -> str:
        return f"MefExposureFile({self.path!r}, layout={self.layout.name!r})"

    # -- ExposureSource --------------------------------------------------------------

    def header(self) -> ExposureHeader:
        """Identity, band, WCS, shape and valid region, from the headers only."""
        with open_mef(self.path) as headers:
            meta = self._meta(headers)
        if self.background is not None:
            with open_mef(self.background) as bkg:
                self._background_index(bkg, meta.header.shape)
        return meta.header

    def load(self, box: Box | None = None) -> Exposure:
        """The exposure, or its cutout over ``box`` (detector pixels, clipped)."""
        return self._load(box, None)

    def load_described(self, header: ExposureHeader, box: Box | None = None) -> Exposure:
        """:meth:`load`, with ``header`` (what :meth:`header` returned) instead of
        parsing the file's headers again: only the pixels are read."""
        return self._load(box, header)

    def _load(self, box: Box | None, described: ExposureHeader | None) -> Exposure:
        with open_mef(self.path) as headers:
            meta = self._meta(headers, described)
            cut = cutout_box(meta.header, box)
            image = headers.pixels(meta.image, cut, "image")
            mask = headers.pixels(meta.mask, cut, "mask")
            plane = headers.pixels(meta.plane, cut, "variance/weight")
            background = None
            if meta.background is not None and self.background is None:
                background = headers.pixels(meta.background, cut, "background")
            if not np.issubdtype(mask.dtype, np.integer):
                raise headers.fail(meta.mask, f"the mask must be integer, got {mask.dtype}")
            names = meta.header.mask_bits
            # before narrowing to int32: bits above 31 of a wider mask would vanish
            unknown = names.unknown_bits(mask.astype(np.int64, copy=False))
            if unknown:
                raise headers.fail(
                    meta.mask,
                    f"mask bits {unknown & 0xFFFFFFFFFFFFFFFF:#x} have no name "
                    f"(named: {sorted(names.bits)})",
                )
            mask = mask.astype(np.int32)
        if self.background is not None:
            with open_mef(self.background) as bkg:
                index = self._background_index(bkg, meta.header.shape)
                background = bkg.pixels(index, cut, "background")
        if background is not None:
            image = image - background
        variance = self._variance(plane, mask, meta)
        try:
            return Exposure(
                image=image,
                # the canonical WCS shifted: canonical too (it pickles exactly; tested)
                wcs=shifted_wcs(meta.header.wcs, cut.x_start, cut.y_start),
                wcs_is_canonical=True,
                variance=variance,
                psf=self.psf,
                visit=meta.header.visit,
                detector=meta.header.detector,
                band=meta.header.band,
                zero_point=meta.header.zero_point,
                mask=mask,
                mask_bits=meta.header.mask_bits,
                origin=(cut.x_start, cut.y_start),
            )
        except ExposureError as err:
            raise CellCoaddFormatError(self.path, str(err)) from None

    # -- reading -----------------------------------------------------------------------

    def _variance(self, plane: np.ndarray, mask: np.ndarray, meta: _Meta) -> np.ndarray:
        if self.layout.weight_hdu is None:
            return plane
        weight = plane.astype(np.float64)
        bad = ~(weight > 0) | ~np.isfinite(weight)
        with np.errstate(divide="ignore", invalid="ignore"):
            variance = np.where(bad, np.nan, 1.0 / weight)
        mask |= np.int32(meta.header.mask_bits.value(self.layout.zero_weight_bit)) * bad
        return variance

    def _meta(self, headers: MefFile, described: ExposureHeader | None = None) -> _Meta:
        """Where the planes are and what the headers say (``described``, when given)."""
        layout = self.layout
        image = headers.index(layout.image_hdu, "image")
        mask = headers.index(layout.mask_hdu, "mask")
        plane_ref = layout.variance_hdu if layout.variance_hdu is not None else layout.weight_hdu
        plane_what = "variance" if layout.variance_hdu is not None else "weight"
        plane = headers.index(plane_ref, plane_what)  # type: ignore[arg-type]
        shape = headers.dims(image, "image")
        for index, what in ((mask, "mask"), (plane, plane_what)):
            dims = headers.dims(index, what)
            if dims != shape:
                raise headers.fail(
                    index, f"the {what} has shape {dims}, the image HDU {image} {shape}"
                )
        background = None
        if not layout.background_subtracted:
            if layout.background_hdu is not None:
                background = headers.index(layout.background_hdu, "background")
                if headers.dims(background, "background") != shape:
                    raise headers.fail(background, f"the background is not of shape {shape}")
            elif self.background is None:
                raise headers.fail(
                    image, "the image is not background subtracted: give a background file"
                )
        if described is not None:
            if described.shape != shape:
                raise headers.fail(image, f"shape {shape}, described as {described.shape}")
            return _Meta(described, image, mask, plane, background)
        primary, image_header = headers.header(0), headers.header(image)
        searched = [(0, primary), (image, image_header)] if image != 0 else [(0, primary)]
        wcs_header = _astropy_header(image_header, shape)
        wcs = canonical_wcs(_wcs(self.path, wcs_header, f"HDU {headers.label(image)}"))
        exposure_header = ExposureHeader(
            visit=self._identity(headers, searched, layout.visit_keys, self.visit, "visit"),
            detector=self._identity(
                headers, searched, layout.detector_keys, self.detector, "detector"
            ),
            band=self._band(headers, searched),
            wcs=wcs,
            shape=shape,
            valid_box=Box.from_shape(shape),
            zero_point=self._zero_point(headers, searched),
            mask_bits=self._mask_bits(headers, mask),
        )
        return _Meta(
            header=exposure_header,
            image=image,
            mask=mask,
            plane=plane,
            background=background,
        )

    def _identity(
        self,
        headers: MefFile,
        searched: list[tuple[int, fitsio.FITSHDR]],
        keys: tuple[str, ...],
        given: int | None,
        what: str,
    ) -> int:
        if given is not None:
            return given
        for key in keys:
            for index, header in searched:
                if key in header:
                    value = header[key]
                    if isinstance(value, str) and value.strip().lstrip("-").isdigit():
                        value = int(value)
                    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                        raise headers.fail(index, f"{key} = {value!r} is not an integer {what}")
                    return int(value)
        hdus = [headers.label(i) for i, _ in searched]
        raise CellCoaddFormatError(
            self.path, f"no {what} keyword {list(keys)} in HDUs {hdus}: {_give(what)}"
        )

    def _band(self, headers: MefFile, searched: list[tuple[int, fitsio.FITSHDR]]) -> str:
        if self.band is not None:
            return self.band
        for key in self.layout.band_keys:
            for _, header in searched:
                value = header.get(key)
                if isinstance(value, str) and value.strip():
                    return value.strip()
        filter_key = self.layout.filter_key
        if filter_key is not None:
            for _, header in searched:
                value = header.get(filter_key)
                if isinstance(value, str) and value.split():
                    return value.split()[0].split("_")[0]
        keys = [*self.layout.band_keys, *([filter_key] if filter_key else [])]
        hdus = [headers.label(i) for i, _ in searched]
        raise CellCoaddFormatError(
            self.path, f"no band keyword {keys} in HDUs {hdus}: {_give('band')}"
        )

    def _zero_point(self, headers: MefFile, searched: list[tuple[int, fitsio.FITSHDR]]) -> float:
        for key in self.layout.zero_point_keys:
            for index, header in searched:
                if key.keyword in header:
                    raw = header[key.keyword]
                    if key.kind == "photocalib":  # an object in the file's afw archive
                        value = photocalib_zero_point(headers, key.keyword) if index == 0 else None
                    else:
                        value = zero_point_from(key.kind, raw)
                    if value is not None:
                        return value
                    # BUNIT may name another unit, and only the primary header's PhotoCalib
                    # reference is read: no zero point from these, and no error
                    if key.kind not in ("bunit", "photocalib"):
                        # present but unusable: never fall back to zero_point= silently
                        raise headers.fail(
                            index,
                            f"{key.keyword} = {raw!r} is not a usable zero point (a finite "
                            f"number{', positive' if key.kind == 'fluxmag0' else ''} is needed)",
                        )
        if self.zero_point is not None:
            return float(self.zero_point)
        keys = [key.keyword for key in self.layout.zero_point_keys]
        hdus = [headers.label(i) for i, _ in searched]
        raise CellCoaddFormatError(
            self.path,
            f"no zero point: no usable keyword {keys} in HDUs {hdus}; {_give('zero_point')}",
        )

    def _mask_bits(self, headers: MefFile, mask: int) -> MaskBits:
        layout = self.layout
        bits = dict(layout.mask_bits) if layout.mask_bits is not None else {}
        if layout.mask_bits is None:
            header = headers.header(mask)
            for key in header.keys():
                if key.upper().startswith("MP_"):
                    value = header[key]
                    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                        raise headers.fail(mask, f"{key} = {value!r} is not a bit number")
                    bits[key[3:].upper()] = int(value)
            if not bits:
                raise headers.fail(mask, "no MP_<NAME> mask-plane keywords")
        if layout.weight_hdu is not None and layout.zero_weight_bit not in bits:
            free = [b for b in range(31) if b not in bits.values()]
            if not free:
                raise headers.fail(mask, "no free mask bit for zero weights")
            bits[layout.zero_weight_bit] = free[0]
        try:
            return MaskBits(bits=bits)
        except ValueError as err:
            raise headers.fail(mask, f"bad mask-bit definitions ({err})") from None

    def _background_index(self, headers: MefFile, shape: tuple[int, int]) -> int:
        index = None
        for i in range(len(headers.fits)):
            if headers.fits[i].get_extname().strip().upper() == "SCI":
                index = i
                break
        if index is None:
            for i in range(len(headers.fits)):
                hdu = headers.fits[i]
                if hdu.get_exttype() == "IMAGE_HDU" and len(hdu.get_dims()) == 2:
                    index = i
                    break
        if index is None:
            raise headers.fail(None, "no background image HDU")
        dims = headers.dims(index, "background")
        if dims != shape:
            raise headers.fail(index, f"the background has shape {dims}, the image {shape}")
        return index


def _give(field: str) -> str:
    """How to give a value the file lacks: the manifest field a user writes first."""
    return (
        f"set `{field} = ...` in the file's manifest entry (manifest.toml), or {field}= "
        "when reading it in Python"
    )


def read_mef_exposure(
    path: PathLike,
    layout: MefLayout,
    psf: PsfLike | PathLike,
    **options: Any,
) -> Exposure:
    """The whole detector exposure of ``path`` (options: see :class:`MefExposureFile`)."""
    return MefExposureFile(path, layout, psf, **options).load()


def read_lsst_exposure(
    path: PathLike,
    psf: PsfLike | PathLike,
    zero_point: float | None = None,
    **options: Any,
) -> Exposure:
    """An LSST pipelines single-detector ``ExposureF`` file (``calexp``, ``visit_image``).

    The PSF, stored by the pipelines in an afw archive HDU cellcoadd cannot read, is
    required (a model, or a ``.psf`` PSFEx / Piff file). The zero point comes from
    ``FLUXMAG0`` or ``BUNIT = 'nJy'`` (31.4) when present, else from ``zero_point``.
    """
    return MefExposureFile(path, LSST_LAYOUT, psf, zero_point=zero_point, **options).load()


def read_des_exposure(
    image_path: PathLike,
    psf_path: PsfLike | PathLike,
    bkg_path: PathLike | None = None,
    *,
    zero_point: float | None = None,
    **options: Any,
) -> Exposure:
    """A DES single-epoch file (``SCI``/``MSK``/``WGT``), its PSFEx model and optional
    ``_bkg`` background file; zero point from ``MAGZERO``/``MAGZP`` else ``zero_point``."""
    source = MefExposureFile(
        image_path, DES_LAYOUT, psf_path, zero_point=zero_point, background=bkg_path, **options
    )
    return source.load()
