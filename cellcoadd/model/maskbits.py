"""Named mask bits, stored with every mask so no raw integer travels without its names."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from pydantic import BaseModel, ConfigDict, field_validator

DEFAULT_BITS: dict[str, int] = {
    "BAD": 0,  # detector defect
    "SAT": 1,  # saturated
    "CR": 2,  # cosmic ray
    "EDGE": 3,  # detector edge
    "NO_DATA": 4,  # no input data (empty coadd cell, or outside the valid region)
    "INTRP": 5,  # interpolated over
    "SUSPECT": 6,  # near saturation / non-linear
    "STREAK": 7,  # satellite trail
}


class MaskBits(BaseModel):
    """Mapping of mask-bit names to bit numbers (0 to 30; the plane is int32).

    Examples
    --------
    >>> bits = MaskBits()
    >>> bits.value("SAT") | bits.value("CR")
    6
    >>> bits.names(6)
    ['SAT', 'CR']
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    bits: dict[str, int] = dict(DEFAULT_BITS)

    @field_validator("bits")
    @classmethod
    def _check_bits(cls, bits: dict[str, int]) -> dict[str, int]:
        for name, bit in bits.items():
            if not name or not name.replace("_", "").isalnum():
                raise ValueError(f"mask bit name {name!r} must be alphanumeric (underscores ok)")
            if not 0 <= bit <= 30:
                raise ValueError(f"mask bit {name!r} = {bit} is outside 0..30 (int32 plane)")
        if len(set(bits.values())) != len(bits):
            raise ValueError(f"mask bits share a bit number: {bits}")
        return bits

    def value(self, name: str) -> int:
        """Integer value ``1 << bit`` of one named bit."""
        try:
            return 1 << self.bits[name]
        except KeyError:
            raise KeyError(f"unknown mask bit {name!r}; known: {sorted(self.bits)}") from None

    def mask_of(self, names: Iterable[str]) -> int:
        """OR of the values of several named bits."""
        out = 0
        for name in names:
            out |= self.value(name)
        return out

    @property
    def all_bits(self) -> int:
        """OR of every defined bit."""
        return self.mask_of(self.bits)

    def names(self, value: int) -> list[str]:
        """Names of the bits set in ``value``, in bit order."""
        return [n for n, b in sorted(self.bits.items(), key=lambda kv: kv[1]) if value >> b & 1]

    def unknown_bits(self, mask: np.ndarray) -> int:
        """OR of the bits set anywhere in ``mask`` that have no name here (0 if none)."""
        present = int(np.bitwise_or.reduce(mask, axis=None)) if mask.size else 0
        return present & ~self.all_bits
