"""Configuration of a coadd build, stored with every coadd it produced."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    field_validator,
    model_serializer,
    model_validator,
)

from cellcoadd.errors import ConfigError
from cellcoadd.model.mask_presets import MASK_PRESETS
from cellcoadd.model.units import (
    NJY_ZERO_POINT,
    PixelUnit,
    check_units,
    is_njy_zero_point,
    normalise_unit,
)

#: Default side of the coadd PSF stamp, coadd pixels: at 0.2 arcsec per pixel it holds
#: all but 7e-5 of the flux of the simulator's widest Moffat PSF (beta = 3.5, FWHM 1.15
#: arcsec; 1.2e-3 is lost at 35 pixels, 4.6e-4 at 51). A 0.7" Kolmogorov PSF, whose wings
#: fall as r^(-11/3), still loses 1.5e-3 (5.4e-3 at 35; 2e-4 at 249, the whole outer box
#: of a default cell): see ``InputRecord.psf_flux_outside`` and
#: :class:`~cellcoadd.errors.PsfStampWarning`.
DEFAULT_PSF_SIZE = 75


class BuildConfig(BaseModel):
    """How cells are coadded (frozen; written into every output file).

    Parameters
    ----------
    n_noise : int
        Number K of noise realizations per cell.
    psf_size : int, optional
        Side of the odd, square coadd PSF stamp, coadd pixels. Left out (None), a build
        uses :data:`DEFAULT_PSF_SIZE` (75), or the largest odd size the cells' outer box
        holds if that is smaller (:meth:`resolved`); the coadds' metadata records the
        size used. The flux of each input's PSF outside the stamp is measured and
        recorded (``InputRecord.psf_flux_outside``); the stamp is renormalised to unit
        sum, so a stamp too small for the PSF changes its size (a few 1e-3 of flux lost
        at 35 pixels for a 0.7" Kolmogorov PSF biases shear estimators that use the PSF
        stamp's normalisation, such as BFD, by ~1e-3).
    kernel : "lanczos3"
        Resampling kernel (normalised Lanczos-3; the only one offered).
    max_mask_fraction : float
        An exposure whose masked fraction inside the cell's outer box exceeds this is
        rejected for the cell (reason ``"masked_fraction"``).
    bad_mask_bits : list of str, or "des" or "lsst"
        Names of the exposure mask bits that count as bad: those pixels are interpolated
        from their good neighbours before the warp (image, noise and variance alike) and
        counted in ``mfrac``. Every exposure must define every name here, unless the name
        is also in ``optional_mask_bits``. A survey's name gives its preset
        (:data:`~cellcoadd.model.mask_presets.MASK_PRESETS`), stored as the list of names.
    optional_mask_bits : list of str
        Names in ``bad_mask_bits`` that an exposure may leave undefined (then none of its
        pixels has that bit).
    units : "nJy" or "count"
        Unit of the output pixels. ``"nJy"`` (the default): nanojansky per coadd pixel,
        i.e. counts at the AB zero point ``2.5 log10(3631e9) = 31.4``
        (:data:`~cellcoadd.model.units.NJY_ZERO_POINT`). ``"count"``: counts at
        ``zero_point``. Left out, it is ``"count"`` when a ``zero_point`` is given (so
        configurations and files written before this field existed, which state
        ``zero_point = 30``, keep their meaning), else ``"nJy"``. ``"counts"`` is
        accepted for ``"count"``.
    zero_point : float
        Common AB zero point, mag, to which every input is scaled: the zero point of the
        output pixels. Fixed at 31.4 (:data:`~cellcoadd.model.units.NJY_ZERO_POINT`) for
        nJy; required for counts.
    mapping_tolerance : float
        Maximum error, pixels, allowed of the approximated cell -> exposure pixel mapping.
    noise_variance : "background" or "pixel"
        Variance of the noise realizations: each exposure's background variance (the
        median of its variance plane over the valid pixels, the same value that sets its
        weight), so they carry no image of the sources even where the variance plane
        includes the sources' Poisson noise; or ``"pixel"``, each pixel's own variance.
    psf_corners : bool
        Also store the coadd PSF at the 4 corner pixels of each cell's inner box
        (``CellCoadd.psf_corners``, format 1.4), with the same inputs and weights as the
        centre's, so that :meth:`CellCoadd.psf_at` interpolates the PSF across the cell.
        Each input's corner stamp is its centre stamp plus what changes between the
        centre and the corner, rendered from the exposure's oversampled PSF cores (drawn
        once per exposure at a grid of nodes, interpolated at the corner): it equals the
        PSF drawn and warped at the corner to ~1e-4 in size and shape. Off by default:
        ~9% of a build where each exposure's PSF is constant, 16-29% with varying models
        (3 x 3 core draws per exposure region; measured in ``docs/shear.md``); it needs
        ``psf_size // 2 <= cell_border`` (each corner stamp lies in the outer box). Left
        out of the stored JSON when off, so configurations and files from before it keep
        their bytes and hashes.
    psf_phase : bool
        Also store each used input's resampling phase term (``CellCoadd.psf_phase`` and
        ``psf_maps``, format 1.5: its effective PSF oversampled around the cell centre, its
        affine map and weight, :mod:`cellcoadd.model.psf_phase`), so that
        :meth:`CellCoadd.psf_at` gives the PSF of a star at any pixel of the cell, with
        the phase at which each input meets it (without it the stamps hold the phases of
        their own pixels only). With ``psf_corners`` too it equals a star's coadded image
        to ~1e-4 anywhere in the inner box, DECam PSFEx included. Off by default: ~5% of
        a build alone; with the corners ~10% where each exposure's PSF is constant and
        20-29% with varying models, over the 10% a default may cost; 17 kB per used input
        and cell (cost and accuracy: ``docs/shear.md``). Left out of the stored JSON when
        off, like ``psf_corners``.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    n_noise: int = Field(3, ge=0, le=64)
    psf_size: int | None = Field(
        None,
        ge=3,
        description="odd side of the coadd PSF stamp, px; left out: 75, or the largest odd "
        "size the cells' outer box holds",
    )
    kernel: Literal["lanczos3"] = "lanczos3"
    max_mask_fraction: float = Field(0.1, ge=0.0, le=1.0)
    bad_mask_bits: tuple[str, ...] = ("BAD", "SAT", "CR", "NO_DATA", "EDGE")
    optional_mask_bits: tuple[str, ...] = ()
    units: PixelUnit = Field(
        "nJy", description="output pixel unit: nJy, or count (counts at zero_point)"
    )
    zero_point: float = Field(
        NJY_ZERO_POINT,
        gt=-50.0,
        lt=100.0,
        description="mag, AB zero point of the output pixels (31.4 = 2.5 log10(3631e9) for nJy)",
    )
    mapping_tolerance: float = Field(1e-3, gt=0.0, le=0.1, description="pixels")
    noise_variance: Literal["background", "pixel"] = "background"
    psf_corners: bool = Field(
        False,
        description="also store the coadd PSF at the 4 corner pixels of each cell's inner box",
    )

    psf_phase: bool = Field(
        False,
        description="also store each used input's resampling phase term, for psf_at",
    )

    @model_serializer(mode="wrap")
    def _drop_psf_corners_off(self, handler: Any) -> dict[str, Any]:
        # absent when off: configurations, hashes and files from before them are unchanged
        data = handler(self)
        for flag in ("psf_corners", "psf_phase"):
            if data.get(flag, True) is False:
                del data[flag]
        return data

    @model_validator(mode="before")
    @classmethod
    def _units_and_zero_point(cls, data: Any) -> Any:
        # units left out: counts when a zero point is stated (configurations and files
        # from before the units field), else nJy
        if not isinstance(data, dict):
            return data
        data = dict(data)
        if "units" in data:
            data["units"] = normalise_unit(data["units"]) or data["units"]
        else:
            data["units"] = "count" if data.get("zero_point") is not None else "nJy"
        zero_point = data.get("zero_point")
        if (
            data["units"] == "nJy"
            and isinstance(zero_point, (int, float))
            and not isinstance(zero_point, bool)
            and is_njy_zero_point(float(zero_point))
        ):
            data["zero_point"] = NJY_ZERO_POINT  # the exact value, whatever its rounding
        return data

    @model_validator(mode="after")
    def _check_units(self) -> BuildConfig:
        check_units(self.units, self.zero_point, "zero_point" in self.model_fields_set)
        return self

    def required_mask_bits(self) -> tuple[str, ...]:
        """The names of ``bad_mask_bits`` every exposure must define."""
        return tuple(n for n in self.bad_mask_bits if n not in self.optional_mask_bits)

    @classmethod
    def for_survey(cls, survey: str, **fields: Any) -> BuildConfig:
        """The configuration for a survey's exposure files: its ``bad_mask_bits`` preset.

        Parameters
        ----------
        survey : "des" or "lsst"
            The preset (:data:`~cellcoadd.model.mask_presets.MASK_PRESETS`).
        **fields
            Any other field.

        Examples
        --------
        >>> BuildConfig.for_survey("lsst", n_noise=1).bad_mask_bits
        ('BAD', 'SAT', 'CR', 'EDGE', 'NO_DATA')
        """
        return cls(bad_mask_bits=survey, **fields)

    @field_validator("bad_mask_bits", mode="before")
    @classmethod
    def _preset(cls, value: Any) -> Any:
        if isinstance(value, str):  # a survey preset; one bit name is a list of one
            preset = MASK_PRESETS.get(value.strip().lower())
            if preset is None:
                raise ConfigError(
                    f"unknown mask-bit preset {value!r}: give one of {sorted(MASK_PRESETS)} "
                    "or a list of bit names"
                )
            return preset
        return value

    def resolved(self, outer_side: int) -> BuildConfig:
        """This configuration with ``psf_size`` set for cells whose outer box has
        ``outer_side`` pixels on its shorter side (itself when ``psf_size`` is set).

        Left out, ``psf_size`` becomes :data:`DEFAULT_PSF_SIZE` or the largest odd size
        not exceeding ``outer_side``, whichever is smaller.
        """
        if self.psf_size is not None:
            return self
        largest = outer_side if outer_side % 2 else outer_side - 1
        return self.model_copy(update={"psf_size": max(3, min(DEFAULT_PSF_SIZE, largest))})

    @property
    def stamp_size(self) -> int:
        """``psf_size`` of a resolved configuration (:meth:`resolved`).

        Raises
        ------
        ConfigError
            When ``psf_size`` was left out and not resolved for a cell size.
        """
        if self.psf_size is None:
            raise ConfigError("psf_size is not set: resolve it for the cells' outer box first")
        return self.psf_size

    @field_validator("psf_size")
    @classmethod
    def _odd(cls, size: int | None) -> int | None:
        if size is None:
            return None
        if size % 2 == 0:
            raise ConfigError(
                f"psf_size must be odd so the stamp has a central pixel, got {size}", value=size
            )
        return size
