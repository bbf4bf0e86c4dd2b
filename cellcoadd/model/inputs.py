"""One record per input exposure that overlaps a cell: what was used, what was rejected and why."""

from __future__ import annotations

import struct
import unicodedata
from enum import Enum
from typing import Annotated

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    WithJsonSchema,
    field_validator,
    model_validator,
)

from cellcoadd.errors import CellCoaddValueError, InvalidCoaddError


class InputStatus(str, Enum):
    """Status of an input in a cell: ``USED`` or the reason it was rejected.

    Members are strings (``InputStatus.EDGE == "edge"``), which is how files store them.
    Extend by appending a reason here; stored files then need a major format version
    bump, because older readers cannot represent the new value.
    """

    USED = "used"
    NO_OVERLAP = "no_overlap"  # no pixel of the cell's outer box lands on the exposure
    EDGE = "edge"  # the exposure does not cover the outer box plus the kernel's reach
    MASKED_FRACTION = "masked_fraction"  # too many bad pixels under the cell
    BAD_WEIGHT = "bad_weight"  # background variance not positive, finite, representable
    BAD_PSF = "bad_psf"  # the PSF model could not be drawn at the cell centre
    BAD_PIXELS = "bad_pixels"  # non-finite pixels that no bad mask bit flags
    BAND_MISMATCH = "band_mismatch"  # the exposure's band is not the build's

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)


#: Every valid status, ``"used"`` first.
INPUT_STATUSES: tuple[str, ...] = tuple(status.value for status in InputStatus)

#: The statuses that mean "rejected", in declaration order.
REJECTION_REASONS: tuple[str, ...] = INPUT_STATUSES[1:]

#: The float fields of a record (stored as float64 columns by the file formats).
FLOAT_FIELDS: tuple[str, ...] = (
    "weight",
    "overlap_fraction",
    "psf_fwhm",
    "psf_e1",
    "psf_e2",
    "psf_T",
    "zero_point",
    "psf_flux_outside",
)


def check_band_name(band: str) -> str:
    """Validate a filter name: non-empty, no surrounding whitespace, no control characters.

    Any other Unicode is allowed (e.g. ``"y\\u00b2"``). Surrounding whitespace is refused
    because fixed-width FITS strings cannot keep it.
    """
    if not band:
        raise CellCoaddValueError("band must be a non-empty string", value=band)
    if band != band.strip():
        raise CellCoaddValueError(
            f"band {band!r} must not start or end with whitespace", value=band
        )
    if any(unicodedata.category(char).startswith("C") for char in band):
        raise CellCoaddValueError(
            f"band {band!r} must not contain control or unassigned characters", value=band
        )
    return band


class InputRecord(BaseModel):
    """One input exposure (visit, detector) considered for one cell.

    Parameters
    ----------
    visit, detector : int
        Identity of the input exposure.
    band : str
        Filter of the exposure (Unicode allowed; see :func:`check_band_name`).
    weight : float
        Coadd weight, ``1 / background variance`` at the common zero point (>= 0, finite);
        0 exactly when the input was rejected, > 0 when it was used.
    status : InputStatus or str
        ``"used"`` or the rejection reason, one of :data:`REJECTION_REASONS` (stored as
        the string value of an :class:`InputStatus`).
    overlap_fraction : float
        Fraction (0..1) of the cell's outer box covered by the exposure's valid box.
    psf_fwhm : float
        FWHM of the round Gaussian with the PSF's second-moment determinant,
        ``2 sqrt(2 ln 2) det(M)^(1/4)``, arcsec (NaN when it could not be measured).
    psf_e1, psf_e2 : float
        PSF ellipticity as *distortions* (not reduced shears):
        ``e1 = (Ixx - Iyy) / (Ixx + Iyy)``, ``e2 = 2 Ixy / (Ixx + Iyy)``, ``|e| = (a^2 -
        b^2) / (a^2 + b^2)``, in the coadd's pixel frame (``x`` West, ``y`` North for the
        tract's TAN projection; NaN allowed).
    psf_T : float
        PSF size ``T = Ixx + Iyy``, arcsec^2; ``2 sigma^2`` for a round Gaussian of
        standard deviation ``sigma`` (NaN allowed).
    zero_point : float
        Photometric zero point of the exposure, mag (NaN allowed).
    psf_flux_outside : float
        Fraction of the flux of the exposure's PSF model (unit flux, pixel included) that
        falls outside the cell's coadd PSF stamp once warped onto the coadd grid: the
        part the stamp's renormalisation to unit sum leaves out. NaN for rejected inputs
        and in files written before format 1.3.

    Notes on the PSF moments: ``I`` are GalSim HSM adaptive (elliptical-Gaussian-weighted)
    second moments, equal to the unweighted ones for a Gaussian, of the exposure's PSF
    *as warped onto the coadd's pixel grid* at the cell centre (the contribution the
    coadd PSF averages, pixel response included), converted to arcsec with the coadd
    WCS's local Jacobian (see :func:`cellcoadd.builder.psf.psf_moments`). Rejected inputs
    have NaN.

    Notes
    -----
    Records compare with ``==`` field by field, so two records holding NaN are never
    equal; :meth:`identical` compares floats bit for bit instead.
    """

    # statuses are kept as their string values, which is what files hold
    model_config = ConfigDict(
        frozen=True, extra="forbid", ser_json_inf_nan="constants", use_enum_values=True
    )

    visit: int
    detector: int
    band: str
    weight: float = Field(ge=0.0, allow_inf_nan=False)
    # the schema inlines the values (a plain string enum), as files store them
    status: Annotated[
        InputStatus,
        WithJsonSchema({"enum": list(INPUT_STATUSES), "title": "Status", "type": "string"}),
    ]
    overlap_fraction: float = Field(ge=0.0, le=1.0)
    psf_fwhm: float = Field(
        description="arcsec, FWHM of the round Gaussian of the same second-moment "
        "determinant, 2 sqrt(2 ln 2) det(M)^(1/4)"
    )
    psf_e1: float = Field(
        description="distortion (Ixx - Iyy) / (Ixx + Iyy) of the PSF's adaptive moments "
        "on the coadd pixel grid (x West, y North); not a reduced shear"
    )
    psf_e2: float = Field(
        description="distortion 2 Ixy / (Ixx + Iyy) of the PSF's adaptive moments on the "
        "coadd pixel grid (x West, y North); not a reduced shear"
    )
    psf_T: float = Field(
        description="arcsec^2, T = Ixx + Iyy of the PSF's adaptive moments on the coadd "
        "pixel grid (2 sigma^2 for a round Gaussian)"
    )
    zero_point: float = Field(description="mag")
    psf_flux_outside: float = Field(
        float("nan"),
        description="fraction of the PSF model's flux outside the cell's coadd PSF stamp",
    )

    @field_validator("band")
    @classmethod
    def _check_band(cls, band: str) -> str:
        return check_band_name(band)

    @model_validator(mode="after")
    def _check_weight_matches_status(self) -> InputRecord:
        if self.status == InputStatus.USED and not self.weight > 0.0:
            raise InvalidCoaddError(
                f"input (visit={self.visit}, detector={self.detector}) is used but has "
                f"weight {self.weight}; a used input needs a positive weight",
                visit=self.visit,
                detector=self.detector,
                value=self.weight,
            )
        if self.status != InputStatus.USED and self.weight != 0.0:
            raise InvalidCoaddError(
                f"input (visit={self.visit}, detector={self.detector}) was rejected "
                f"({self.status}) but has weight {self.weight}; rejected inputs have weight 0",
                visit=self.visit,
                detector=self.detector,
                value=self.weight,
            )
        return self

    @property
    def is_used(self) -> bool:
        """Whether the input contributed to the cell."""
        return self.status == InputStatus.USED

    @property
    def key(self) -> tuple[int, int]:
        """``(visit, detector)``."""
        return (self.visit, self.detector)

    def identical(self, other: InputRecord) -> bool:
        """Whether every field is equal, comparing floats bit for bit (so NaN matches NaN)."""
        if not isinstance(other, InputRecord):
            return False
        if (self.visit, self.detector, self.band, self.status) != (
            other.visit,
            other.detector,
            other.band,
            other.status,
        ):
            return False
        return all(
            _float_bits(getattr(self, name)) == _float_bits(getattr(other, name))
            for name in FLOAT_FIELDS
        )


def _float_bits(value: float) -> bytes:
    # NaN payloads and -0.0 survive a round trip, so compare the IEEE-754 bytes.
    return struct.pack("<d", value)
