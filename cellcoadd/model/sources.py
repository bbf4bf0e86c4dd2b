"""Exposures loaded on demand: what a build knows of an input before reading its pixels.

A survey patch has hundreds of input exposures; holding them all in memory (and copying
them into every worker) does not scale. An :class:`ExposureSource` says what an exposure
is from its headers alone (:class:`ExposureHeader`: identity, band, WCS, shape, valid
region) and loads its pixels, cut to a box of detector pixels, when a cell needs them.
Sources are small picklable objects (paths and options), so each worker process loads
its own inputs. :class:`cellcoadd.io.ExposureFile` (cellcoadd's own files) and
:class:`cellcoadd.io.MefExposureFile` (LSST, DES and other layouts) implement them;
any object with the same two methods works too.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

from astropy.wcs import WCS

from cellcoadd.errors import CellCoaddTypeError, InputError
from cellcoadd.geometry.box import Box
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.maskbits import MaskBits


@dataclass(frozen=True, eq=False)
class ExposureHeader:
    """What a build needs to know of an exposure before reading its pixels.

    Attributes
    ----------
    visit, detector : int
        Identity.
    band : str
        Filter name.
    wcs : astropy.wcs.WCS
        Celestial WCS of the whole detector image (0-based pixels).
    shape : (int, int)
        ``(ny, nx)`` of the detector image, pixels.
    valid_box : Box
        Detector pixels that hold data (half-open).
    zero_point : float
        Photometric zero point of the pixels, mag.
    mask_bits : MaskBits
        Names of the bits of its mask.
    """

    visit: int
    detector: int
    band: str
    wcs: WCS
    shape: tuple[int, int]
    valid_box: Box
    zero_point: float
    mask_bits: MaskBits

    @property
    def key(self) -> tuple[int, int]:
        """``(visit, detector)``."""
        return (self.visit, self.detector)


class ExposureSource(ABC):
    """An exposure that can be described now and loaded later, in any process."""

    @abstractmethod
    def header(self) -> ExposureHeader:
        """Identity, band, WCS, shape and valid region, from headers only (no pixels)."""

    @abstractmethod
    def load(self, box: Box | None = None) -> Exposure:
        """The exposure, or its cutout over ``box`` (detector pixels, half-open, clipped
        to the detector): an :class:`Exposure` whose ``origin`` is the box's start and
        whose WCS describes the cutout."""

    def load_described(self, header: ExposureHeader, box: Box | None = None) -> Exposure:
        """:meth:`load`, given ``header``, what :meth:`header` returned (here or in
        another process). Sources that can reuse it, e.g. its WCS instead of parsing
        the file's again, override this; the result must be :meth:`load`'s."""
        return self.load(box)


def cutout_box(header: ExposureHeader, box: Box | None) -> Box:
    """``box`` clipped to the detector (the whole detector for None).

    Raises
    ------
    ValueError
        When ``box`` does not overlap the detector.
    """
    full = Box.from_shape(header.shape)
    if box is None:
        return full
    if not box.overlaps(full):
        raise InputError(
            f"exposure (visit={header.visit}, detector={header.detector}): box {box} is "
            f"outside the detector {full}",
            visit=header.visit,
            detector=header.detector,
            value=box,
            allowed=full,
        )
    return box.intersection(full)


@dataclass(frozen=True, eq=False)
class DescribedSource:
    """A source with its header read once (what a build hands to its workers)."""

    source: ExposureSource
    header: ExposureHeader

    @property
    def key(self) -> tuple[int, int]:
        return self.header.key

    def load(self, box: Box | None = None) -> Exposure:
        source = self.source
        if isinstance(source, ExposureSource):
            return source.load_described(self.header, box)
        return source.load(box)  # any object with header() and load()


def describe(item: Exposure | ExposureSource | DescribedSource) -> Exposure | DescribedSource:
    """An in-memory exposure as it is; a source with its header read (once).

    Raises
    ------
    TypeError
        For anything else.
    """
    if isinstance(item, (Exposure, DescribedSource)):
        return item
    if isinstance(item, ExposureSource):
        return DescribedSource(item, item.header())
    raise CellCoaddTypeError(
        f"an input must be an Exposure or an ExposureSource, got {item!r}",
        allowed=(Exposure, ExposureSource),
    )


def header_of(item: Exposure | DescribedSource) -> Exposure | ExposureHeader:
    """What selection needs before pixels: the exposure itself or the source's header
    (both have ``visit``, ``detector``, ``band``, ``wcs``, ``shape``, ``valid_box``,
    ``zero_point``, ``mask_bits`` and ``key``)."""
    return item if isinstance(item, Exposure) else item.header
