"""Where the inputs of a coadd were observed: instrument, and per visit the physical filter
and observing day, as Rubin's data butler names them (kept so that a Rubin coadd read in and
written back out says the same)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator

from cellcoadd.errors import CellCoaddValueError

#: Longest instrument or physical-filter name kept (Rubin's tables hold 32 characters).
MAX_NAME = 32


class VisitInfo(BaseModel):
    """One visit: its id, physical filter (e.g. ``"r_57"``) and ``day_obs`` (YYYYMMDD)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    visit: int
    physical_filter: str = Field(max_length=MAX_NAME)
    day_obs: int = Field(ge=0, description="observing day, YYYYMMDD (0: unknown)")


class Observations(BaseModel):
    """The instrument that took a coadd's inputs and what is known of each visit.

    Parameters
    ----------
    instrument : str
        Instrument name as Rubin's butler knows it (``"LSSTCam"``, ``"LSSTComCam"``...).
    visits : tuple of VisitInfo
        One entry per visit, sorted by visit id, no visit twice.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    instrument: str = Field(min_length=1, max_length=MAX_NAME)
    visits: tuple[VisitInfo, ...] = ()

    @field_validator("visits")
    @classmethod
    def _sorted_unique(cls, visits: tuple[VisitInfo, ...]) -> tuple[VisitInfo, ...]:
        ids = [v.visit for v in visits]
        if len(set(ids)) != len(ids):
            raise CellCoaddValueError("a visit is listed twice", value=ids)
        return tuple(sorted(visits, key=lambda v: v.visit))

    def visit(self, visit: int) -> VisitInfo | None:
        """The entry of ``visit``, or None."""
        for info in self.visits:
            if info.visit == visit:
                return info
        return None
