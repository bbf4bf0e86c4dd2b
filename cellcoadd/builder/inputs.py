"""The inputs of a build, in one shape, and the set-up every build of cells starts with.

An input is either an in-memory :class:`~cellcoadd.model.exposure.Exposure` or an
exposure source (:class:`~cellcoadd.model.sources.ExposureSource`: paths and options,
its header read once here). The builder sees one shape, :class:`BuildInput`: what
selection reads before any pixel (the header), and the pixels over a box on demand. An
in-memory exposure is the trivial case: it is its own header, and loading gives it whole.
:func:`prepare` checks the inputs of a build together (unique, one band when asked, every
required mask bit named) and gathers what every block of cells shares
(:class:`BuildSettings`); :func:`~cellcoadd.builder.patch.build_patch` and
:func:`~cellcoadd.builder.cell.build_cells` both start with it.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from cellcoadd.builder.exposure_frame import ExposureFrame, exposure_frame
from cellcoadd.errors import ConfigError, InputError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.tract import Cell
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.inputs import check_band_name
from cellcoadd.model.mask_presets import fitting_presets
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.sources import DescribedSource, ExposureHeader, ExposureSource, describe


@dataclass(frozen=True, eq=False)
class BuildInput:
    """One input of a build.

    Attributes
    ----------
    header : Exposure or ExposureHeader
        What selection reads before pixels (``visit``, ``detector``, ``band``, ``wcs``,
        ``shape``, ``valid_box``, ``zero_point``, ``mask_bits``): the exposure itself
        when it is in memory.
    source : DescribedSource or None
        Where the pixels are loaded from; None for an in-memory exposure.
    """

    header: Exposure | ExposureHeader
    source: DescribedSource | None = None

    @classmethod
    def of(cls, item: Exposure | ExposureSource | DescribedSource | BuildInput) -> BuildInput:
        """The input of an exposure, a source (its header read here, once) or an input.

        Raises
        ------
        TypeError
            For anything else.
        """
        if isinstance(item, BuildInput):
            return item
        described = describe(item)
        if isinstance(described, Exposure):
            return cls(described)
        return cls(described.header, described)

    @property
    def key(self) -> tuple[int, int]:
        """``(visit, detector)``."""
        return self.header.key

    def load(self, box: Box) -> tuple[Exposure, tuple[int, int]]:
        """Its pixels over at least ``box`` (header pixels, clipped to the detector), and
        the header pixel ``(x, y)`` of the loaded image's first pixel.

        A source loads its cutout over ``box``; an in-memory exposure is returned whole,
        at ``(0, 0)``.
        """
        if self.source is None:
            assert isinstance(self.header, Exposure)  # how `of` builds it
            return self.header, (0, 0)
        exposure = self.source.load(box)
        return exposure, exposure.origin


@dataclass(frozen=True, eq=False)
class BuildSettings:
    """What every block of cells of one build shares.

    Attributes
    ----------
    config : BuildConfig
        Build settings, with ``psf_size`` resolved for the cells (:meth:`BuildConfig.resolved`).
    seed : int
        Seed of the noise realizations.
    mask_bits : MaskBits
        Bit definitions of the output masks.
    band : str or None
        The band of the coadds; inputs of another band are recorded as ``band_mismatch``.
    area : Box
        Tract pixels the inputs are mapped over: every cell built lies inside, and every
        block of the build uses the same mapping.
    record_distant : bool
        Record inputs whose projected valid box misses a cell as ``no_overlap``; a patch
        build leaves them out of the cell's inputs instead.
    """

    config: BuildConfig
    seed: int
    mask_bits: MaskBits
    band: str | None
    area: Box
    record_distant: bool = True


@dataclass(frozen=True, eq=False)
class PreparedBuild:
    """The checked inputs of a build, their frames over its area, and its settings."""

    inputs: list[BuildInput]
    frames: list[ExposureFrame | None]
    settings: BuildSettings

    def candidates(self, cells: Sequence[Cell]) -> list[int]:
        """Indices of the inputs that may serve some of ``cells`` (of the build's area),
        from their frames: every other input would leave those cells' records and pixels
        as they are (:meth:`~cellcoadd.builder.cell.CellBlock.add` makes the same
        decision per cell first). Inputs not mapped (another band) are left out."""
        return [
            k
            for k, frame in enumerate(self.frames)
            if frame is not None and any(frame.may_serve(cell.outer_bbox) for cell in cells)
        ]


def check_mask_bits(exposures: Sequence[Exposure | ExposureHeader], config: BuildConfig) -> None:
    """Refuse exposures that do not define every required bad-mask bit by name.

    Raises
    ------
    InputError
        Naming the exposure and the missing bits (list them in
        ``BuildConfig.optional_mask_bits`` if the exposure really has no such pixels).
    """
    required = config.required_mask_bits()
    for exposure in exposures:
        missing = [name for name in required if name not in exposure.mask_bits.bits]
        if missing:
            raise InputError(
                f"exposure (visit={exposure.visit}, detector={exposure.detector}) does not "
                f"define the mask bits {missing} named in bad_mask_bits (it defines "
                f"{sorted(exposure.mask_bits.bits)}); {_preset_hint(exposure.mask_bits.bits)}"
                "map its bit names, or list them in BuildConfig.optional_mask_bits"
            )


def _preset_hint(defined: Iterable[str]) -> str:
    """Advice naming the survey presets whose bits an exposure defines, or ``""``."""
    names = fitting_presets(defined)
    if not names:
        return ""
    name = names[0]
    return (
        f"its bits fit the {name!r} preset: bad_mask_bits = {name!r} in the configuration "
        f"file or BuildConfig.for_survey({name!r}) (= {name.upper()}_BAD_MASK_BITS); else "
    )


def check_unique_inputs(exposures: Sequence[Exposure | ExposureHeader]) -> None:
    """Refuse duplicate ``(visit, detector)`` pairs (they would be coadded twice).

    Raises
    ------
    InputError
        Naming the pair (a ValueError too).
    """
    seen: set[tuple[int, int]] = set()
    for exposure in exposures:
        if exposure.key in seen:
            raise InputError(f"duplicate input (visit, detector) = {exposure.key}")
        seen.add(exposure.key)


def _the_one_band(headers: Sequence[Exposure | ExposureHeader]) -> str:
    """The band of all ``headers``; refuses none, several, or a name a coadd cannot record."""
    bands = sorted({header.band for header in headers})
    if not bands:
        raise InputError("build_patch needs at least one exposure")
    if len(bands) > 1:
        first = {b: next(h for h in headers if h.band == b) for b in bands}
        named = ", ".join(
            f"{b!r} (visit={h.visit}, detector={h.detector})" for b, h in first.items()
        )
        raise InputError(
            f"exposures of several bands given: {named}; build one band at a time", value=bands
        )
    try:
        check_band_name(bands[0])
    except ValueError as err:
        raise InputError(f"band {bands[0]!r} cannot be recorded in a coadd: {err}") from None
    return bands[0]


def prepare(
    cells: Sequence[Cell],
    exposures: Sequence[Exposure | ExposureSource | DescribedSource | BuildInput],
    config: BuildConfig,
    seed: int,
    *,
    mask_bits: MaskBits | None = None,
    band: str | None = None,
    one_band: bool = False,
    area: Box | None = None,
    record_distant: bool = True,
    frames: Sequence[ExposureFrame | None] | None = None,
) -> PreparedBuild:
    """Check the inputs of a build of ``cells`` (one tract) and map each over its area.

    Parameters
    ----------
    one_band : bool
        Require every input to be of one band (a patch), which becomes the band; else
        ``band`` (default: the first input's), inputs of other bands being recorded as
        ``band_mismatch``.
    area : Box, optional
        Tract pixels the inputs are mapped over (default: the bounding box of the cells'
        outer boxes).
    frames : sequence of ExposureFrame or None, optional
        The inputs' frames over ``area``, if already computed; None entries (and inputs
        of another band, which are not mapped) are computed here.

    Other parameters as for :func:`~cellcoadd.builder.cell.build_cell`.

    Raises
    ------
    InputError
        On duplicate ``(visit, detector)`` inputs, with ``one_band`` none or several
        bands, or when an input lacks a required mask bit (a ValueError too).
    ConfigError
        Without cells.
    """
    inputs = [BuildInput.of(item) for item in exposures]  # a source's header is read here
    headers = [item.header for item in inputs]
    check_unique_inputs(headers)
    if one_band:
        band = _the_one_band(headers)
    elif band is None and headers:
        band = headers[0].band
    check_mask_bits(headers, config)  # before any work
    mask_bits = mask_bits or MaskBits.union(header.mask_bits for header in headers)
    if not cells:
        raise ConfigError("a block needs at least one cell")
    area = area or Box.enclosing([cell.outer_bbox for cell in cells])
    # a psf_size left out is fixed here, for the smallest outer box of the build
    config = config.resolved(min(min(cell.outer_bbox.shape) for cell in cells))
    settings = BuildSettings(config, seed, mask_bits, band, area, record_distant)
    given = list(frames) if frames is not None else [None] * len(inputs)
    tract_wcs = cells[0].tract_wcs
    # exposures covering the same part of the area share their interpolation weights
    grids: dict = {}
    mapped: list[ExposureFrame | None] = []
    for header, frame in zip(headers, given, strict=True):
        if frame is None and header.band == band:
            frame = exposure_frame(tract_wcs, area, header, config.mapping_tolerance, grids)
        mapped.append(frame)
    return PreparedBuild(inputs, mapped, settings)


__all__ = [
    "BuildInput",
    "BuildSettings",
    "PreparedBuild",
    "check_mask_bits",
    "check_unique_inputs",
    "prepare",
]
