"""All cells of one patch with the metadata they share, and stitching of their inner regions."""

from __future__ import annotations

import copy
import math
import re
from collections.abc import Iterable, Iterator, Mapping
from functools import cached_property
from typing import Any, Literal, NamedTuple

import numpy as np
from astropy.wcs import WCS
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    field_validator,
    model_serializer,
    model_validator,
)

from cellcoadd._version import __version__
from cellcoadd.errors import (
    CellCoaddIncompatibleValuesError,
    CellCoaddRangeError,
    CellCoaddTypeError,
    CellCoaddValueError,
    InvalidCoaddError,
)
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.geometry.regions import NearestCenterRegion
from cellcoadd.geometry.tract import Patch, Tract
from cellcoadd.geometry.wcs_utils import shifted_wcs
from cellcoadd.model import planes as cell_planes
from cellcoadd.model.aperture_corrections import ApertureCorrections
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.cell_common import CellCommon
from cellcoadd.model.inputs import check_band_name
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.observations import Observations
from cellcoadd.model.units import (
    NJY_ZERO_POINT,
    PixelUnit,
    check_units,
    mask_plane_cards,
    stored_units,
    unit_cards_by_kind,
)

#: Version ``"MAJOR.MINOR"`` of the stored data model and file layouts. A major bump means
#: readers of older majors cannot read the files (they refuse them); a minor bump only adds
#: (fields, datasets, keywords), so readers of the same major read newer minors.
#: 1.1: FITS ``DATACRC`` keywords. 1.2: ``units`` is an astropy unit string (``"nJy"`` or
#: ``"count"``) and ``zero_point`` a field (older files' free text is mapped on reading),
#: ``BuildConfig.units``; ``BUNIT``/``MAGZERO``/``MP_*`` keywords and attributes.
#: 1.3: optional ``observations`` and ``skymap_config.name``/``tangent_pixel`` (Rubin's
#: sky map); compressed FITS float planes as floats with ``CCNFBITS``; WCS cards on every
#: FITS pixel-plane HDU.
#: also in 1.3: a ``psf_flux_outside`` column in the inputs tables (NaN when read from older
#: files); ``BuildConfig.psf_size`` may be left out (builds record the size they used).
#: 1.4: the optional plane ``psf_corners`` (``BuildConfig.psf_corners``; the FITS column
#: ``HDU_PSF_CORNERS``, -1 without it; an HDF5 dataset listed in ``contents`` when stored).
#: 1.5: the optional planes ``psf_phase`` and ``psf_maps`` (``BuildConfig.psf_phase``), one
#: layer per used input (``HDU_PSF_PHASE``, ``HDU_PSF_MAPS``, as ``psf_corners``).
#: also in 1.5: the optional ``aperture_corrections`` (kept from a Rubin coadd's ``APCORR``).
#: 1.6: an empty cell's planes stored without pixels (FITS ``CCEMPTY`` header-only HDUs,
#: HDF5 ``(0,)`` datasets with ``empty``; see :mod:`cellcoadd.io.coadd.empty_cells`): a
#: 1.5 reader refuses such a file.
FORMAT_VERSION = "1.6"

#: The first format version whose ``units`` is an astropy unit string.
UNITS_VERSION = (1, 2)

_VERSION_PATTERN = re.compile(r"^(\d+)\.(\d+)$")

#: Planes that can be stitched: those on the cell grid (the type checker's copy of
#: :func:`~cellcoadd.model.planes.grid_plane_names`; a test keeps them equal).
Plane = Literal["image", "mask", "variance", "mfrac", "noise"]


class Stitched(NamedTuple):
    """A plane stitched over the patch inner box, with the WCS of its pixels.

    ``wcs`` maps array pixel ``(0, 0)`` (0-based, ``array[0, 0]``) to the sky position of
    tract pixel ``(bbox.x_start, bbox.y_start)``, exactly as each cell's ``wcs`` does for
    its outer-box arrays, so a pixel of ``array`` and the same pixel of a cell map to the
    same sky position.
    """

    array: np.ndarray
    wcs: WCS
    bbox: Box


def parse_format_version(version: str) -> tuple[int, int]:
    """``(major, minor)`` of a ``"MAJOR.MINOR"`` string (ValueError if malformed)."""
    match = _VERSION_PATTERN.match(version)
    if match is None:
        raise CellCoaddValueError(
            f"format version {version!r} is not of the form MAJOR.MINOR", value=version
        )
    return int(match.group(1)), int(match.group(2))


def _before_units(version: object) -> bool:
    """Whether metadata of ``version`` predate unit strings (free-text ``units``)."""
    if not isinstance(version, str):
        return False
    try:
        return parse_format_version(version) < UNITS_VERSION
    except ValueError:
        return False


def _build_zero_point(config: object) -> float | None:
    """The zero point a (raw or validated) build configuration states, if any."""
    if isinstance(config, BuildConfig):
        return config.zero_point
    if isinstance(config, dict):
        value = config.get("zero_point")
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    return None


class PatchMetadata(BaseModel):
    """Metadata shared by all cells of a patch (frozen; stored as JSON in every file).

    Parameters
    ----------
    skymap_config : SkyMapConfig
        Geometry of the sky map (cell and patch sizes, pixel scale).
    tract : int
        Tract number.
    tract_center : (float, float)
        ``(ra, dec)`` of the tract's tangent point, deg.
    patch : (int, int)
        Patch index ``(px, py)`` inside the tract.
    band : str
        Filter name (Unicode allowed).
    units : "nJy" or "count"
        Unit of the image and noise planes (the variance is in its square), an astropy
        unit string: ``"nJy"`` (nanojansky per coadd pixel) or ``"count"`` (counts at
        ``zero_point``). See :mod:`cellcoadd.model.units`. The free text of files before
        format 1.2 (``"counts at zero point 30 per coadd pixel"``) is mapped on reading.
    zero_point : float
        AB zero point of the pixel values, mag: a source of magnitude ``m`` sums to
        ``10**(-0.4 (m - zero_point))`` in ``units``. Exactly
        :data:`~cellcoadd.model.units.NJY_ZERO_POINT` (31.4) for nJy, filled in when left
        out; for counts it is required (taken from ``build_config`` when left out).
    mask_bits : MaskBits
        Names of the mask bits; must define ``NO_DATA``.
    build_config : BuildConfig
        How the cells were built; the source of :attr:`n_noise` and :attr:`psf_size`.
    software_version : str
        cellcoadd version that built the coadd.
    format_version : str
        ``"MAJOR.MINOR"`` of the data model (:data:`FORMAT_VERSION` when created).
    observations : Observations or None
        Instrument, and physical filter and observing day of each visit, when known (from
        a Rubin coadd); left out of the stored JSON when None.
    aperture_corrections : ApertureCorrections or None
        Per-cell aperture corrections, when known (from a Rubin coadd's ``APCORR``); left
        out of the stored JSON when None.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    skymap_config: SkyMapConfig
    tract: int = Field(ge=0)
    tract_center: tuple[float, float] = Field(description="(ra, dec) of the tangent point, deg")
    patch: tuple[int, int]
    band: str
    units: PixelUnit = Field(
        description="astropy unit string of the image and noise planes (the variance is in "
        "its square): nJy, or count (counts at zero_point)"
    )
    zero_point: float = Field(
        NJY_ZERO_POINT,
        gt=-50.0,
        lt=100.0,
        description="mag, AB zero point of the pixel values (31.4 for nJy)",
    )
    mask_bits: MaskBits = Field(default_factory=MaskBits)
    build_config: BuildConfig = Field(default_factory=BuildConfig)
    software_version: str = __version__
    format_version: str = FORMAT_VERSION
    observations: Observations | None = None
    aperture_corrections: ApertureCorrections | None = None

    @model_serializer(mode="wrap")
    def _drop_unknown_observations(self, handler: Any) -> dict[str, Any]:
        # added after format 1.2: absent when unknown, so such files stay byte-identical
        data = handler(self)
        for key in ("observations", "aperture_corrections"):
            if data.get(key, 0) is None:
                del data[key]
        return data

    @field_validator("band")
    @classmethod
    def _check_band(cls, band: str) -> str:
        return check_band_name(band)

    @model_validator(mode="before")
    @classmethod
    def _map_units(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        return stored_units(
            data,
            before_units=_before_units(data.get("format_version")),
            build_zero_point=_build_zero_point(data.get("build_config")),
        )

    @model_validator(mode="after")
    def _check_units(self) -> PatchMetadata:
        check_units(self.units, self.zero_point, "zero_point" in self.model_fields_set)
        return self

    @field_validator("tract_center")
    @classmethod
    def _check_center(cls, center: tuple[float, float]) -> tuple[float, float]:
        ra, dec = center
        if not (math.isfinite(ra) and 0.0 <= ra < 360.0 and math.isfinite(dec)):
            raise InvalidCoaddError(
                f"tract_center ra must be in [0, 360) deg, got {ra}", value=ra, allowed=(0.0, 360.0)
            )
        if not -90.0 <= dec <= 90.0:
            raise InvalidCoaddError(
                f"tract_center dec must be in [-90, 90] deg, got {dec}",
                value=dec,
                allowed=(-90.0, 90.0),
            )
        return center

    @field_validator("format_version")
    @classmethod
    def _check_version(cls, version: str) -> str:
        parse_format_version(version)
        return version

    @field_validator("mask_bits")
    @classmethod
    def _check_no_data(cls, mask_bits: MaskBits) -> MaskBits:
        if "NO_DATA" not in mask_bits.bits:
            raise InvalidCoaddError("mask_bits must define NO_DATA (it flags pixels without data)")
        return mask_bits

    @model_validator(mode="after")
    def _check_patch(self) -> PatchMetadata:
        n = self.skymap_config.patches_per_tract
        if not all(0 <= p < n for p in self.patch):
            raise InvalidCoaddError(
                f"patch {self.patch} is outside the tract's {n} x {n} patches",
                value=self.patch,
                allowed=(0, n),
            )
        return self

    @property
    def unit(self) -> Any:
        """:attr:`units` as an ``astropy.units.Unit``."""
        import astropy.units as u

        return u.Unit(self.units)

    @cached_property
    def cell_common(self) -> CellCommon:
        """What every cell of the patch carries (:attr:`CellCoadd.common`)."""
        return CellCommon(
            units=self.units,
            zero_point=self.zero_point,
            band=self.band,
            mask_bits=self.mask_bits,
            tract=self.tract,
            patch=self.patch,
            skymap=self.skymap_config.name,
        )

    def unit_cards(self) -> dict[str, list[tuple[str, object, str]]]:
        """``BUNIT`` (and for counts ``MAGZERO``) keywords of the planes in flux or flux
        squared (``image``, ``noise``, ``variance``), and ``MP_<NAME> = bit`` keywords of
        the mask-bit plane (``mask``), as ``(name, value, comment)`` by plane (each plane's
        :attr:`~cellcoadd.model.planes.PlaneSpec.unit`): FITS header cards and HDF5
        attributes.

        Mask-bit names that are not upper-case ASCII (letters, digits, ``_``) are left
        out (FITS keywords cannot hold them); the metadata JSON names every bit.
        """
        by_kind = unit_cards_by_kind(self.units, self.zero_point)
        by_kind["mask_bits"] = mask_plane_cards(self.mask_bits.bits)
        return {
            spec.name: by_kind[spec.unit] for spec in cell_planes.PLANES if spec.unit in by_kind
        }

    @property
    def n_noise(self) -> int:
        """Number ``K`` of noise realizations per cell (from ``build_config``)."""
        return self.build_config.n_noise

    @property
    def cell_plane_names(self) -> tuple[str, ...]:
        """Names of the planes its build gives each cell, in storage order: the required
        ones, and each optional one whose ``build_config`` flag
        (:attr:`~cellcoadd.model.planes.PlaneSpec.config_flag`, e.g. ``psf_corners``)
        asks for it."""
        return tuple(
            spec.name
            for spec in cell_planes.PLANES
            if not spec.optional
            or (spec.config_flag is not None and getattr(self.build_config, spec.config_flag))
        )

    @property
    def psf_size(self) -> int:
        """Side of the PSF stamp, pixels (from ``build_config``; when it leaves the size out,
        the size a build uses for these cells, :meth:`BuildConfig.resolved`)."""
        return self.build_config.resolved(self.skymap_config.cell_outer).stamp_size

    @property
    def cell_inner(self) -> int:
        """Side of a cell's inner box, pixels."""
        return self.skymap_config.cell_inner

    @property
    def cell_border(self) -> int:
        """Border added on each side of a cell's inner box, pixels."""
        return self.skymap_config.cell_border

    @property
    def cell_outer(self) -> int:
        """Side of a cell's outer box, pixels."""
        return self.skymap_config.cell_outer

    @property
    def format_major(self) -> int:
        return parse_format_version(self.format_version)[0]

    @cached_property
    def geometry(self) -> Patch:
        """The patch as a :class:`~cellcoadd.geometry.Patch` (its tract, cells and boxes)."""
        ra, dec = self.tract_center
        center = (ra, dec)
        tract = Tract(
            id=self.tract,
            center=center,
            config=self.skymap_config,
            inner_region=NearestCenterRegion((center,), 0),
        )
        return tract.patch(*self.patch)

    @property
    def patch_inner_bbox(self) -> Box:
        """The patch's inner box in tract pixels (tiled by its inner cells' inner boxes)."""
        return self.geometry.inner_bbox

    @property
    def inner_cell_indices(self) -> list[tuple[int, int]]:
        """Tract-global indices of the inner cells, row by row (``cy`` outer, ``cx`` inner)."""
        return self.geometry.inner_cell_indices

    @property
    def all_cell_indices(self) -> list[tuple[int, int]]:
        """Indices of the inner cells and the ``patch_border_cells`` rings around them."""
        return self.geometry.cell_indices

    def cell_boxes(self, index: tuple[int, int]) -> tuple[Box, Box]:
        """``(inner, outer)`` boxes of cell ``index`` implied by the sky-map configuration."""
        cell = self.geometry.tract.cell(*index)
        return cell.inner_bbox, cell.outer_bbox


def check_patch_cell(
    metadata: PatchMetadata,
    key: tuple[int, int],
    cell: object,
    allowed: set[tuple[int, int]] | None = None,
) -> None:
    """Refuse (InvalidCoaddError) ``cell`` as the cell ``key`` of the patch of ``metadata``
    unless it is a :class:`CellCoadd` of that index, one of the patch's cells (``allowed``:
    :attr:`PatchMetadata.all_cell_indices`, computed when not given), in its tract, with the
    boxes implied by the sky map, ``n_noise`` realizations, a ``psf_size`` stamp and only
    named mask bits; an empty cell must have ``NO_DATA`` in every mask pixel."""
    if not isinstance(cell, CellCoadd):
        raise InvalidCoaddError(f"cell {key}: expected a CellCoadd, got {type(cell).__name__}")
    if cell.index != key:
        raise InvalidCoaddError(f"cell stored under {key} has index {cell.index}")
    if key not in (set(metadata.all_cell_indices) if allowed is None else allowed):
        raise InvalidCoaddError(
            f"cell {key} is not an inner or border cell of patch {metadata.patch}"
        )
    if cell.tract != metadata.tract:
        raise InvalidCoaddError(f"cell {key} is in tract {cell.tract}, not {metadata.tract}")
    inner, outer = metadata.cell_boxes(key)
    if (cell.inner_bbox, cell.outer_bbox) != (inner, outer):
        raise InvalidCoaddError(
            f"cell {key} has boxes inner={cell.inner_bbox}, outer={cell.outer_bbox}; "
            f"the sky map implies inner={inner}, outer={outer}"
        )
    if cell.n_noise != metadata.n_noise:
        raise InvalidCoaddError(
            f"cell {key} has {cell.n_noise} noise realizations, "
            f"the build config says {metadata.n_noise}"
        )
    if cell.psf.shape != (metadata.psf_size, metadata.psf_size):
        raise InvalidCoaddError(
            f"cell {key} has a {cell.psf.shape} PSF stamp, expected side {metadata.psf_size}"
        )
    unknown = metadata.mask_bits.unknown_bits(cell.mask)
    if unknown:
        raise InvalidCoaddError(f"cell {key}: mask has bits {unknown:#x} with no name")
    no_data = metadata.mask_bits.value("NO_DATA")
    if cell.is_empty and not np.all(cell.mask & no_data):
        raise InvalidCoaddError(f"cell {key} is empty but its mask lacks NO_DATA somewhere")


def check_planes(cell: CellCoadd, present: tuple[str, ...], *, optional_only: bool = False) -> None:
    """Refuse (InvalidCoaddError) ``cell`` unless it holds exactly the planes ``present``
    (:attr:`CellCoadd.plane_names`): all the cells of a patch hold the same planes, those
    its build declares (:attr:`PatchMetadata.cell_plane_names`). ``optional_only``: look
    at the optional planes only (the required ones are checked by the cell itself).

    The error names the cell (``cell=``) and the first plane at fault (``value=``; the
    planes expected are ``allowed=``)."""
    names = [spec.name for spec in cell_planes.PLANES if spec.optional or not optional_only]
    held = tuple(name for name in names if getattr(cell, name, None) is not None)
    wanted = tuple(name for name in present if name in names)
    if held != wanted:
        missing = [name for name in wanted if name not in held]
        extra = [name for name in held if name not in wanted]
        plane = (missing or extra)[0]
        raise InvalidCoaddError(
            f"cell {cell.index} {'lacks' if missing else 'has'} the plane {plane!r}: it "
            f"holds the {'optional ' if optional_only else ''}planes {list(held)}, the "
            f"patch's cells hold {list(wanted)} (as its build configuration declares): all the "
            "cells of a patch hold the same planes",
            cell=cell.index,
            value=plane,
            allowed=tuple(present),
        )


class PatchCoadd(Mapping[tuple[int, int], CellCoadd]):
    """The cells (inner and border) of one patch, read-only mapping ``(cx, cy) -> CellCoadd``.

    Parameters
    ----------
    metadata : PatchMetadata
        Shared metadata.
    cells : mapping (cx, cy) -> CellCoadd
        Cells of the patch; any may be missing. Each must belong to the patch
        (:attr:`PatchMetadata.all_cell_indices`), be stored under its own index, lie in the
        metadata's tract, have the boxes implied by the sky map, ``n_noise`` realizations,
        a ``psf_size`` stamp, only named mask bits and exactly the planes its build
        declares (:attr:`PatchMetadata.cell_plane_names`: an optional plane its
        configuration asks for, none it does not); an empty cell must have ``NO_DATA`` set
        in every mask pixel.

    Examples
    --------
    >>> cell = patch_coadd[3, 4]              # doctest: +SKIP
    >>> image = patch_coadd.stitch("image")   # doctest: +SKIP
    >>> image, wcs, bbox = patch_coadd.stitched("image")   # doctest: +SKIP
    >>> nddata = patch_coadd.to_nddata((3, 4))  # doctest: +SKIP
    """

    def __init__(self, metadata: PatchMetadata, cells: Mapping[tuple[int, int], CellCoadd]) -> None:
        if not isinstance(metadata, PatchMetadata):
            raise CellCoaddTypeError(
                f"metadata must be a PatchMetadata, got {type(metadata).__name__}",
                allowed=PatchMetadata,
            )
        self.metadata = metadata
        allowed = set(metadata.all_cell_indices)
        checked: dict[tuple[int, int], CellCoadd] = {}
        present = metadata.cell_plane_names
        for key, cell in cells.items():
            key = (int(key[0]), int(key[1]))
            check_patch_cell(metadata, key, cell, allowed)
            check_planes(cell, present, optional_only=True)  # those its build declares
            checked[key] = cell
        common = metadata.cell_common
        for key, cell in checked.items():  # a cell taken from the patch describes itself
            if cell.common != common:
                # a shallow copy (the arrays are shared): a cell given here may belong to
                # another patch too, whose description it keeps
                cell = copy.copy(cell)
                cell.attach(common)
                checked[key] = cell
        self.cells: dict[tuple[int, int], CellCoadd] = {k: checked[k] for k in sorted(checked)}

    @property
    def has_psf_corners(self) -> bool:
        """Whether the cells have :attr:`CellCoadd.psf_corners` (all or none do)."""
        return any(cell.psf_corners is not None for cell in self.cells.values())

    def __getitem__(self, index: tuple[int, int]) -> CellCoadd:
        return self.cells[index]

    def __iter__(self) -> Iterator[tuple[int, int]]:
        return iter(self.cells)

    def __len__(self) -> int:
        return len(self.cells)

    @property
    def inner_cell_indices(self) -> list[tuple[int, int]]:
        """Indices of the cells whose inner boxes tile the patch inner box (present or not)."""
        return self.metadata.inner_cell_indices

    @property
    def empty_cell_indices(self) -> list[tuple[int, int]]:
        """Indices of the stored cells with no used input."""
        return [key for key, cell in self.cells.items() if cell.is_empty]

    @property
    def patch_inner_bbox(self) -> Box:
        """The region covered by :meth:`stitch`, in tract pixels."""
        return self.metadata.patch_inner_bbox

    @property
    def stitch_wcs(self) -> WCS:
        """WCS of the arrays :meth:`stitch` returns (array pixel ``(0, 0)`` is tract pixel
        ``(x_start, y_start)`` of :attr:`patch_inner_bbox`).

        Taken from a stored cell's WCS, shifted (so the stitched pixels map to the same
        sky positions as the cells' pixels), or from the sky map when no cell is stored.
        """
        box = self.patch_inner_bbox
        for cell in self.cells.values():
            outer = cell.outer_bbox
            return shifted_wcs(cell.wcs, box.x_start - outer.x_start, box.y_start - outer.y_start)
        return shifted_wcs(self.metadata.geometry.tract.wcs, box.x_start, box.y_start)

    def stitched(self, plane: Plane = "image", noise_index: int | None = None) -> Stitched:
        """:meth:`stitch` together with the WCS and the tract-pixel box of the array.

        Returns
        -------
        Stitched
            Named tuple ``(array, wcs, bbox)``: the array of :meth:`stitch`,
            :attr:`stitch_wcs` and :attr:`patch_inner_bbox`.
        """
        return Stitched(self.stitch(plane, noise_index), self.stitch_wcs, self.patch_inner_bbox)

    def psf_at(self, x: float, y: float, *, extrapolate: bool = False) -> np.ndarray:
        """The coadd PSF of a point source at pixel ``(x, y)`` of the stitched arrays.

        ``(x, y)`` are array pixels of :meth:`stitch` (``(0, 0)`` is tract pixel
        ``(x_start, y_start)`` of :attr:`patch_inner_bbox`, pixel centres at integers); the
        PSF is that of the inner cell whose inner box holds the position
        (:meth:`CellCoadd.psf_at`, whose accuracy and requirements apply).

        Raises
        ------
        CellCoaddRangeError
            When ``(x, y)`` lies outside the patch's inner box.
        CellCoaddValueError
            When the cell there is not stored, or cannot give a PSF away from its centre
            (:meth:`CellCoadd.psf_at`).
        """
        box, side = self.patch_inner_bbox, self.metadata.cell_inner
        tx, ty = float(x) + box.x_start, float(y) + box.y_start
        for axis, value, low, n in (("x", x, -0.5, box.nx), ("y", y, -0.5, box.ny)):
            if not low <= value < n - 0.5:
                raise CellCoaddRangeError(
                    f"{axis} = {value} is outside the stitched patch [{low}, {n - 0.5})",
                    value=value,
                    low=low,
                    high=n - 0.5,
                )
        index = (math.floor((tx + 0.5) / side), math.floor((ty + 0.5) / side))
        cell = self.cells.get(index)
        if cell is None:
            raise CellCoaddValueError(
                f"cell {index}, which holds stitched pixel ({x}, {y}), is not stored",
                cell=index,
            )
        outer = cell.outer_bbox
        return cell.psf_at(tx - outer.x_start, ty - outer.y_start, extrapolate=extrapolate)

    def to_nddata(
        self,
        index: tuple[int, int],
        *,
        bad_bits: Iterable[str] | None = None,
        inner: bool = False,
    ) -> Any:
        """Cell ``index`` as an ``astropy.nddata.CCDData`` in this patch's unit.

        See :meth:`CellCoadd.to_nddata`; the unit, zero point and mask-bit names come from
        the metadata.
        """
        meta = self.metadata
        return self.cells[index].to_nddata(
            meta.units,
            mask_bits=meta.mask_bits,
            bad_bits=bad_bits,
            inner=inner,
            zero_point=meta.zero_point,
        )

    def stitch(self, plane: Plane = "image", noise_index: int | None = None) -> np.ndarray:
        """One contiguous array of a plane over the patch inner box, from inner-cell inner boxes.

        The array alone, as before; :meth:`stitched` returns it with its WCS
        (:attr:`stitch_wcs`).

        Parameters
        ----------
        plane : {"image", "variance", "mfrac", "mask", "noise"}
            Which plane.
        noise_index : int, optional
            Realization to stitch; required for ``plane="noise"`` only.

        Returns
        -------
        ndarray, shape ``(cells_per_patch * cell_inner,) * 2``
            Row 0 / column 0 is pixel ``(y_start, x_start)`` of :attr:`patch_inner_bbox`.
            A missing or empty cell leaves NaN there (float planes) or the ``NO_DATA`` bit
            (mask plane).
        """
        if plane not in cell_planes.grid_plane_names():
            raise CellCoaddValueError(
                f"unknown plane {plane!r}; use image, variance, mfrac, mask or noise",
                value=plane,
                allowed=cell_planes.grid_plane_names(),
            )
        spec = cell_planes.plane(plane)
        if spec.per_realization:
            if noise_index is None or not 0 <= noise_index < self.metadata.n_noise:
                raise CellCoaddRangeError(
                    f"plane 'noise' needs noise_index in [0, {self.metadata.n_noise}), "
                    f"got {noise_index}",
                    value=noise_index,
                    low=0,
                    high=self.metadata.n_noise,
                )
        elif noise_index is not None:
            raise CellCoaddIncompatibleValuesError(
                f"noise_index applies to plane 'noise' only, not {plane!r}",
                values={"plane": plane, "noise_index": noise_index},
            )
        box = self.patch_inner_bbox
        side = self.metadata.cell_inner
        # no data: the NO_DATA bit in integer (mask) planes, NaN in float ones
        if spec.dtype.kind in "iu":
            fill: float = self.metadata.mask_bits.value("NO_DATA")
        else:
            fill = np.nan
        out = np.full(box.shape, fill, dtype=spec.dtype)
        for index in self.inner_cell_indices:
            cell = self.cells.get(index)
            if cell is None or cell.is_empty:
                continue
            views = cell.inner
            values = getattr(views, plane)
            if spec.per_realization:
                values = values[noise_index]
            x0 = index[0] * side - box.x_start
            y0 = index[1] * side - box.y_start
            out[y0 : y0 + side, x0 : x0 + side] = values
        return out

    def equals(self, other: object) -> bool:
        """Whether ``other`` has equal metadata and bit-identical cells under the same indices."""
        if not isinstance(other, PatchCoadd):
            return False
        if self.metadata != other.metadata or list(self.cells) != list(other.cells):
            return False
        return all(cell.equals(other.cells[key]) for key, cell in self.cells.items())

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PatchCoadd):
            return NotImplemented
        return self.equals(other)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        meta = self.metadata
        return (
            f"PatchCoadd(tract={meta.tract}, patch={meta.patch}, band={meta.band!r}, "
            f"cells={len(self.cells)}, empty={len(self.empty_cell_indices)})"
        )
