"""Named mask bits, stored with every mask so no raw integer travels without its names."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from pydantic import BaseModel, ConfigDict, field_validator

from cellcoadd.errors import CellCoaddKeyError, CellCoaddRangeError, CellCoaddValueError

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


#: Bits of the int32 mask plane that can carry a name (0 to 30).
MAX_BITS = 31

#: Longest mask-bit name: FITS stores it as the keyword ``MP_<NAME>`` (a HIERARCH card
#: when longer than 8 characters), which must leave room for its value on an 80-byte card.
MAX_NAME_LENGTH = 32


def _lowest_free(bits: dict[str, int]) -> int:
    used = set(bits.values())
    for bit in range(MAX_BITS):
        if bit not in used:
            return bit
    raise CellCoaddValueError(
        f"more than {MAX_BITS} mask bit names: {sorted(bits)}", value=sorted(bits)
    )


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
        keywords: dict[str, str] = {}
        for name, bit in bits.items():
            # every format must store the name: FITS keywords MP_<NAME> take ASCII letters,
            # digits and underscores, and are case-insensitive
            if not name or not name.isascii() or not name.replace("_", "").isalnum():
                raise CellCoaddValueError(
                    f"mask bit name {name!r} must be ASCII letters, digits and underscores "
                    "(FITS keyword rules)",
                    value=name,
                )
            if len(name) > MAX_NAME_LENGTH:
                raise CellCoaddValueError(
                    f"mask bit name {name!r} is longer than {MAX_NAME_LENGTH} characters",
                    value=name,
                )
            other = keywords.setdefault(name.upper(), name)
            if other != name:
                raise CellCoaddValueError(
                    f"mask bit names {other!r} and {name!r} differ only in case (FITS keywords "
                    "do not)",
                    value=name,
                )
            if not 0 <= bit <= 30:
                raise CellCoaddRangeError(
                    f"mask bit {name!r} = {bit} is outside 0..30 (int32 plane)",
                    value=bit,
                    low=0,
                    high=30,
                )
        if len(set(bits.values())) != len(bits):
            raise CellCoaddValueError(f"mask bits share a bit number: {bits}", value=bits)
        return bits

    def value(self, name: str) -> int:
        """Integer value ``1 << bit`` of one named bit."""
        try:
            return 1 << self.bits[name]
        except KeyError:
            raise CellCoaddKeyError(
                f"unknown mask bit {name!r}; known: {sorted(self.bits)}",
                value=name,
                allowed=sorted(self.bits),
            ) from None

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

    def translation_to(self, target: MaskBits) -> np.ndarray | None:
        """Per bit of this map, the value of the same-named bit in ``target``.

        Returns
        -------
        ndarray of int64, shape (31,), or None
            ``out[b] = 1 << target.bits[name]`` for each ``name`` defined here on bit
            ``b``, 0 for unused bits; None when the numbering is the same (no translation).

        Raises
        ------
        KeyError
            If ``target`` lacks one of this map's names.
        """
        missing = sorted(set(self.bits) - set(target.bits))
        if missing:
            raise CellCoaddKeyError(
                f"mask bits {missing} have no place in {sorted(target.bits)}",
                value=missing,
                allowed=sorted(target.bits),
            )
        if all(target.bits[name] == bit for name, bit in self.bits.items()):
            return None
        out = np.zeros(MAX_BITS, dtype=np.int64)
        for name, bit in self.bits.items():
            out[bit] = 1 << target.bits[name]
        return out

    @classmethod
    def union(cls, maps: Iterable[MaskBits], required: Iterable[str] = ("NO_DATA",)) -> MaskBits:
        """One map holding every name of ``maps`` (and ``required``), by name.

        The first map keeps its numbering; a later name takes its own bit number when
        that is free, else the lowest free bit; ``required`` names missing from all maps
        are added last (default numbering when free). The result depends only on the
        order of ``maps``.

        Raises
        ------
        ValueError
            If more than 31 distinct names are needed.
        """
        bits: dict[str, int] = {}
        for mask_bits in maps:
            for name, bit in mask_bits.bits.items():
                if name not in bits:
                    bits[name] = bit if bit not in bits.values() else _lowest_free(bits)
        for name in required:
            if name not in bits:
                preferred = DEFAULT_BITS.get(name, -1)
                free = preferred >= 0 and preferred not in bits.values()
                bits[name] = preferred if free else _lowest_free(bits)
        return cls(bits=bits)

    def unknown_bits(self, mask: np.ndarray) -> int:
        """OR of the bits set anywhere in ``mask`` that have no name here (0 if none)."""
        present = int(np.bitwise_or.reduce(mask, axis=None)) if mask.size else 0
        return present & ~self.all_bits
