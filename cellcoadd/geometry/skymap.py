"""Sky maps: lists of tracts, from explicit centres or a full-sky ring tessellation."""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, field_validator

from cellcoadd.errors import CellCoaddIndexError, CellCoaddValueError, ConfigError, GeometryError
from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.geometry.regions import (
    NearestCenterRegion,
    RingRegion,
    nearest_center,
    ra_slice_index,
)
from cellcoadd.geometry.tract import Tract

LOCATION_DTYPE = np.dtype(
    [
        ("tract", np.int64),
        ("patch_x", np.int64),
        ("patch_y", np.int64),
        ("cell_x", np.int64),
        ("cell_y", np.int64),
        ("x", np.float64),
        ("y", np.float64),
    ]
)


class SkyMapSpec(BaseModel):
    """Serialisable definition of a sky map (what ``skymap.json`` holds)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["centers", "rings"]
    config: SkyMapConfig
    centers: tuple[tuple[float, float], ...] = ()

    @field_validator("centers")
    @classmethod
    def _check_centers(cls, centers: tuple[tuple[float, float], ...]) -> tuple:
        for ra, dec in centers:
            if not (math.isfinite(ra) and -90.0 <= dec <= 90.0):
                raise GeometryError(
                    f"tract centre ({ra}, {dec}) is not a valid (ra, dec) in deg", value=(ra, dec)
                )
        return tuple((float(ra) % 360.0, float(dec)) for ra, dec in centers)


class SkyMap:
    """An ordered collection of tracts sharing one :class:`SkyMapConfig`.

    Build with :meth:`from_centers` or :meth:`rings`; index with ``skymap[tract_id]``.
    """

    def __init__(self, spec: SkyMapSpec, tracts: list[Tract], rings: list[tuple] | None = None):
        self.spec = spec
        self._tracts = tracts
        # per ring: (first tract id, dec_min, dec_max, n_ra); caps are rings with n_ra == 1
        self._rings = rings

    @property
    def config(self) -> SkyMapConfig:
        return self.spec.config

    # -- construction -------------------------------------------------------------
    @classmethod
    def from_centers(
        cls, centers_deg: Sequence[tuple[float, float]], config: SkyMapConfig | None = None
    ) -> SkyMap:
        """Tracts at explicit ``(ra, dec)`` centres in deg (e.g. a survey field).

        Each tract owns the sky nearer its centre than any other centre, within its pixel
        box; positions outside every tract box belong to no tract (``locate`` gives -1).
        """
        if len(centers_deg) == 0:
            raise GeometryError("from_centers needs at least one tract centre")
        spec = SkyMapSpec(kind="centers", config=config or SkyMapConfig(), centers=centers_deg)
        tracts = [
            Tract(
                id=i,
                center=center,
                config=spec.config,
                inner_region=NearestCenterRegion(spec.centers, i),
            )
            for i, center in enumerate(spec.centers)
        ]
        return cls(spec, tracts)

    @classmethod
    def rings(cls, config: SkyMapConfig | None = None) -> SkyMap:
        """Full-sky tessellation: two polar caps and ``n_rings`` declination rings.

        Ring boundaries are spaced ``180 / (n_rings + 1)`` deg apart, the caps have half
        that radius; each ring is split into equal half-open RA ranges no wider on the sky
        than the ring spacing. Raises ``ValueError`` when tracts (fixed by the patch and
        cell sizes) are too small to cover their inner regions with ``tract_overlap``.
        """
        config = config or SkyMapConfig()
        spacing = 180.0 / (config.n_rings + 1)
        edges = [-90.0 + spacing * (k + 0.5) for k in range(config.n_rings + 1)]
        bands = (
            [(-90.0, edges[0])]
            + list(zip(edges[:-1], edges[1:], strict=True))
            + [(edges[-1], 90.0 + 1e-9)]
        )
        spec = SkyMapSpec(kind="rings", config=config)
        tracts: list[Tract] = []
        rings: list[tuple] = []
        for k, (dec_min, dec_max) in enumerate(bands):
            is_cap = k in (0, len(bands) - 1)
            if is_cap:
                n_ra, dec_center = 1, (-90.0 if k == 0 else 90.0)
            else:
                widest = 0.0 if dec_min < 0.0 < dec_max else min(abs(dec_min), abs(dec_max))
                n_ra = max(1, math.ceil(360.0 * math.cos(math.radians(widest)) / spacing))
                dec_center = 0.5 * (dec_min + dec_max)
            rings.append((len(tracts), dec_min, dec_max, n_ra))
            width = 360.0 / n_ra
            for j in range(n_ra):
                region = RingRegion(dec_min, dec_max, n_ra, j)
                center = ((j + 0.5) * width % 360.0, dec_center)
                tracts.append(Tract(len(tracts), center, config, region))
        skymap = cls(spec, tracts, rings)
        skymap._check_ring_coverage()
        return skymap

    def _check_ring_coverage(self) -> None:
        """Every ring's inner region, plus the overlap margin, must fit in its tract box."""
        cfg = self.config
        margin = cfg.tract_overlap * 3600.0 / cfg.pixel_scale
        for first, dec_min, dec_max, _n_ra in self._rings or []:
            tract = self._tracts[first]
            region = tract.inner_region
            dec_hi = min(dec_max, 90.0)
            t = np.linspace(0.0, 1.0, 41)
            ras = np.concatenate(
                [region.ra_min + region.ra_width * t] * 2
                + [np.full_like(t, region.ra_min), np.full_like(t, region.ra_min + region.ra_width)]
            )
            decs = np.concatenate(
                [
                    np.full_like(t, dec_min),
                    np.full_like(t, dec_hi),
                    dec_min + (dec_hi - dec_min) * t,
                    dec_min + (dec_hi - dec_min) * t,
                ]
            )
            x, y = tract.sky_to_pixel(ras, decs)
            box = tract.bbox
            lo, hi = box.x_start - 0.5 + margin, box.x_stop - 0.5 - margin
            if not (
                np.all(np.isfinite(x))
                and x.min() >= lo
                and x.max() <= hi
                and y.min() >= lo
                and y.max() <= hi
            ):
                raise ConfigError(
                    f"n_rings={cfg.n_rings} gives rings {180.0 / (cfg.n_rings + 1):.3f} deg wide, "
                    f"too wide for tracts of {cfg.tract_size_deg:.3f} deg with "
                    f"tract_overlap={cfg.tract_overlap} deg: increase n_rings or the tract size",
                    value=cfg.n_rings,
                )

    # -- serialisation ------------------------------------------------------------
    def to_json(self) -> str:
        """JSON text that :meth:`from_json` turns back into an identical sky map."""
        return self.spec.model_dump_json(indent=2)

    @classmethod
    def from_json(cls, text: str) -> SkyMap:
        spec = SkyMapSpec.model_validate_json(text)
        if spec.kind == "rings":
            return cls.rings(spec.config)
        return cls.from_centers(spec.centers, spec.config)

    # -- container protocol -------------------------------------------------------
    def __len__(self) -> int:
        return len(self._tracts)

    def __getitem__(self, tract_id: int) -> Tract:
        if not 0 <= tract_id < len(self._tracts):
            raise CellCoaddIndexError(
                f"tract {tract_id} is not in this sky map ({len(self)} tracts)",
                value=tract_id,
                allowed=(0, len(self._tracts)),
            )
        return self._tracts[tract_id]

    def __iter__(self) -> Iterator[Tract]:
        return iter(self._tracts)

    def __repr__(self) -> str:
        return f"SkyMap(kind={self.spec.kind!r}, tracts={len(self)}, config={self.config!r})"

    # -- lookups ------------------------------------------------------------------
    def find_tract(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        """Id of the tract owning each position (deg); -1 where no tract does."""
        ra = np.mod(np.atleast_1d(np.asarray(ra, dtype=float)), 360.0)
        dec = np.atleast_1d(np.asarray(dec, dtype=float))
        if self._rings is None:
            return nearest_center(self.spec.centers, ra, dec)
        ring_starts = np.array([r[0] for r in self._rings])
        ring_dec_min = np.array([r[1] for r in self._rings])
        ring_n_ra = np.array([r[3] for r in self._rings])
        ring = np.searchsorted(ring_dec_min, dec, side="right") - 1
        ring = np.clip(ring, 0, len(self._rings) - 1)
        return ring_starts[ring] + ra_slice_index(ra, ring_n_ra[ring])

    def locate(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        """The unique tract, patch and cell whose inner regions hold each sky position.

        Parameters
        ----------
        ra, dec : array_like
            Positions in deg.

        Returns
        -------
        numpy structured array with fields ``tract, patch_x, patch_y, cell_x, cell_y``
        (tract-global cell indices) and the tract pixel position ``x, y``. Positions that
        no tract owns have ``tract = -1`` and the other indices -1.
        """
        ra = np.mod(np.atleast_1d(np.asarray(ra, dtype=float)), 360.0)
        dec = np.atleast_1d(np.asarray(dec, dtype=float))
        if ra.shape != dec.shape:
            raise CellCoaddValueError(f"ra and dec shapes differ: {ra.shape} vs {dec.shape}")
        out = np.full(ra.shape, -1, dtype=LOCATION_DTYPE)
        out["x"] = np.nan
        out["y"] = np.nan
        tract_ids = self.find_tract(ra, dec)
        cfg = self.config
        for tract_id in np.unique(tract_ids):
            sel = np.nonzero(tract_ids == tract_id)[0]
            tract = self._tracts[int(tract_id)]
            x, y = tract.sky_to_pixel(ra[sel], dec[sel])
            inside = tract.bbox.contains(x, y)
            sel, x, y = sel[inside], x[inside], y[inside]
            cx, cy = tract.cell_of_pixel(x, y)
            out["tract"][sel] = tract_id
            out["cell_x"][sel] = cx
            out["cell_y"][sel] = cy
            out["patch_x"][sel] = cx // cfg.cells_per_patch
            out["patch_y"][sel] = cy // cfg.cells_per_patch
            out["x"][sel] = x
            out["y"][sel] = y
        return out

    def summary(self) -> str:
        """A few lines describing the tessellation and the sizes of its levels."""
        cfg = self.config
        arcmin = cfg.pixel_scale / 60.0
        lines = [
            f"sky map: {self.spec.kind}, {len(self)} tract(s)",
            f"pixel scale: {cfg.pixel_scale} arcsec/pixel",
            f"tract: {cfg.tract_pixels} px = {cfg.tract_size_deg:.3f} deg, "
            f"{cfg.patches_per_tract} x {cfg.patches_per_tract} patches",
            f"patch: inner {cfg.patch_inner} px = {cfg.patch_inner * arcmin:.2f} arcmin, "
            f"{cfg.cells_per_patch} x {cfg.cells_per_patch} inner cells + "
            f"{cfg.patch_border_cells} border cell(s) per side",
            f"cell: inner {cfg.cell_inner} px = {cfg.cell_inner * arcmin:.2f} arcmin, "
            f"outer {cfg.cell_outer} px = {cfg.cell_outer * arcmin:.2f} arcmin "
            f"(border {cfg.cell_border} px)",
        ]
        return "\n".join(lines)
