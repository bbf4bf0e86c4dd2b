"""Sky maps: lists of tracts, from explicit centres or a full-sky ring tessellation."""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from typing import Any, Literal, overload

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_serializer

from cellcoadd.errors import CellCoaddIndexError, CellCoaddValueError, ConfigError, GeometryError
from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.geometry.lsst_rings import LsstRingRegion, LsstRings, lsst_tract_box
from cellcoadd.geometry.regions import (
    NearestCenterRegion,
    RingRegion,
    nearest_center,
    ra_slice_index,
)
from cellcoadd.geometry.tract import Patch, Tract

LOCATION_DTYPE = np.dtype(
    [
        ("tract", np.int64),
        ("patch_x", np.int64),
        ("patch_y", np.int64),
        ("cell_x", np.int64),
        ("cell_y", np.int64),
        ("x", np.float64),
        ("y", np.float64),
        ("patch_id", np.int64),
        ("rubin_cell_x", np.int64),
        ("rubin_cell_y", np.int64),
    ]
)


#: Rubin's cell sky maps by their butler names: the ``SkyMapConfig`` overrides of each
#: (Rubin's ring sky map with the ``cells`` tract builder; sources in docs/geometry.md).
#: ``DC2_cells_v1`` is DESC's name for the geometry of ``lsst_cells_v1``; it keeps its own
#: name (files say ``SKYMAP = 'DC2_cells_v1'``).
LSST_SKYMAPS: dict[str, dict[str, object]] = {
    "lsst_cells_v1": {},
    "lsst_cells_v2": {"cell_border": 0},
    "DC2_cells_v1": {},
}

#: Short names accepted wherever a sky map is named.
SKYMAP_ALIASES = {"lsst": "lsst_cells_v1"}


def known_skymap_names() -> list[str]:
    """Every name :meth:`SkyMap.named` accepts, sorted (the named sky maps and aliases)."""
    return sorted([*LSST_SKYMAPS, *SKYMAP_ALIASES])


def is_known_skymap(name: str) -> bool:
    """Whether :meth:`SkyMap.named` accepts ``name``."""
    return name in LSST_SKYMAPS or name in SKYMAP_ALIASES


def same_geometry(first: SkyMapConfig, second: SkyMapConfig) -> bool:
    """Whether two sky-map configurations give the same tracts, patches and cells (their
    names aside)."""
    return first.model_dump(exclude={"name"}) == second.model_dump(exclude={"name"})


class SkyMapSpec(BaseModel):
    """Serialisable definition of a sky map (what ``skymap.json`` holds).

    ``kind`` is ``"centers"`` (explicit tract centres), ``"rings"`` (our own ring
    tessellation, :meth:`SkyMap.rings`) or ``"lsst"`` (Rubin's ring sky map,
    :meth:`SkyMap.lsst`, with its tracts' RA origin ``ra_start`` in deg).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["centers", "rings", "lsst"]
    config: SkyMapConfig
    centers: tuple[tuple[float, float], ...] = ()
    ra_start: float = Field(0.0, ge=0.0, lt=360.0, description="deg, lsst kind only")

    @model_serializer(mode="wrap")
    def _lsst_fields_only_for_lsst(self, handler: Any) -> dict[str, Any]:
        # other kinds keep the JSON they always had
        data = handler(self)
        if self.kind != "lsst":
            data.pop("ra_start", None)
        return data

    @field_validator("centers")
    @classmethod
    def _check_centers(cls, centers: tuple[tuple[float, float], ...]) -> tuple:
        for ra, dec in centers:
            if not (math.isfinite(ra) and -90.0 <= dec <= 90.0):
                raise GeometryError(
                    f"tract centre ({ra}, {dec}) is not a valid (ra, dec) in deg", value=(ra, dec)
                )
        return tuple((float(ra) % 360.0, float(dec)) for ra, dec in centers)


class _LsstTracts(Sequence[Tract]):
    """The tracts of Rubin's ring sky map, made on first use (18,938 of them by default:
    a lookup or a file read needs only a few)."""

    def __init__(self, layout: LsstRings, config: SkyMapConfig) -> None:
        self._layout, self._config = layout, config
        self._made: dict[int, Tract] = {}

    def __len__(self) -> int:
        return self._layout.n_tracts

    @overload
    def __getitem__(self, index: int) -> Tract: ...
    @overload
    def __getitem__(self, index: slice) -> Sequence[Tract]: ...
    def __getitem__(self, index: int | slice) -> Tract | Sequence[Tract]:
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        tract_id = int(index)
        if tract_id not in self._made:
            region = LsstRingRegion(self._layout, tract_id)
            center = self._layout.center(tract_id)
            self._made[tract_id] = Tract(tract_id, center, self._config, region)
        return self._made[tract_id]


class SkyMap:
    """An ordered collection of tracts sharing one :class:`SkyMapConfig`.

    Build with :meth:`from_centers` or :meth:`rings`; index with ``skymap[tract_id]``.
    """

    def __init__(self, spec: SkyMapSpec, tracts: list[Tract], rings: list[tuple] | None = None):
        self.spec = spec
        self._tracts = tracts
        # per ring: (first tract id, dec_min, dec_max, n_ra); caps are rings with n_ra == 1
        self._rings = rings
        self._lsst: LsstRings | None = None

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
    def lsst(cls, config: SkyMapConfig | None = None, ra_start: float = 0.0) -> SkyMap:
        """Rubin's ring sky map: the tracts, ids, WCSs, patches and cells Rubin uses.

        The same tract ids, tract centres (tangent points), tract boxes and WCSs as LSST's
        ``RingsSkyMap`` (version 1) with its ``cells`` tract builder, so that the same
        position falls in the same tract, patch and cell. With the default configuration
        this is ``lsst_cells_v1`` (18,938 tracts of 30,000 px, 10 x 10 patches of
        20 x 20 cells of 150 + 2 x 50 px at 0.2 arcsec/px); see :meth:`named`.

        Parameters
        ----------
        config : SkyMapConfig, optional
            ``n_rings``, ``tract_overlap`` (deg), ``pixel_scale`` and the cell and patch
            sizes. The number of patches per tract and the tangent pixel follow from
            them (as in Rubin's), so they are filled in; giving a different
            ``patches_per_tract`` or ``tangent_pixel`` explicitly raises ``ConfigError``.
        ra_start : float
            RA (deg) of the first tract of every ring (Rubin's ``raStart``).

        Notes
        -----
        :meth:`rings` is a different tessellation (tract centres at half-slices, one
        tract fewer per ring where the count is an exact integer, caps at RA 180, tangent
        point between pixels); it is kept for files already written. The derivation is
        in ``docs/geometry.md``.
        """
        config = config or SkyMapConfig()
        if not (math.isfinite(ra_start) and 0.0 <= ra_start < 360.0):
            raise ConfigError(f"ra_start must be in [0, 360) deg, got {ra_start}")
        n_patches, tangent = lsst_tract_box(
            config.n_rings, config.tract_overlap, config.pixel_scale, config.patch_inner
        )
        derived = {"patches_per_tract": n_patches, "tangent_pixel": tangent}
        for key, value in derived.items():
            given = getattr(config, key)
            if key in config.model_fields_set and given is not None and given != value:
                raise ConfigError(
                    f"{key}={given} disagrees with Rubin's ring sky map, whose tracts have "
                    f"{key}={value} for n_rings={config.n_rings}, tract_overlap="
                    f"{config.tract_overlap} deg, pixel_scale={config.pixel_scale}, "
                    f"patch inner {config.patch_inner} px: leave it out"
                )
        config = SkyMapConfig.model_validate({**config.model_dump(), **derived})
        layout = LsstRings(config.n_rings, ra_start)
        spec = SkyMapSpec(kind="lsst", config=config, ra_start=ra_start)
        skymap = cls(spec, _LsstTracts(layout, config))  # type: ignore[arg-type]
        skymap._lsst = layout
        return skymap

    @classmethod
    def named(cls, name: str) -> SkyMap:
        """A named cell sky map by its butler name: Rubin's ``lsst_cells_v1`` and
        ``lsst_cells_v2``, DESC's ``DC2_cells_v1`` (the geometry of ``lsst_cells_v1``);
        ``lsst`` is ``lsst_cells_v1``. Raises ``ConfigError`` for other names, listing the
        known ones (:func:`known_skymap_names`)."""
        full = SKYMAP_ALIASES.get(name, name)
        if full not in LSST_SKYMAPS:
            known = ", ".join(known_skymap_names())
            raise ConfigError(f"unknown sky map name {name!r}; known: {known}", value=name)
        return cls.lsst(SkyMapConfig.model_validate({"name": full, **LSST_SKYMAPS[full]}))

    def patch_from_rubin_id(self, tract: int, patch_id: int) -> Patch:
        """The patch of ``tract`` whose Rubin id (the butler's sequential ``patch``,
        ``y * nx + x``) is ``patch_id``: the inverse of :attr:`Patch.rubin_id`."""
        return self[tract].patch_from_rubin_id(patch_id)

    @classmethod
    def rings(cls, config: SkyMapConfig | None = None) -> SkyMap:
        """Our own full-sky tessellation: two polar caps and ``n_rings`` declination rings.

        Not Rubin's ring sky map (use :meth:`lsst` for that): kept for files already
        written. With the defaults it has 18,936 tracts (Rubin's: 18,938), tract centres
        at the middle of each RA slice, caps centred at RA 180 and the tangent point
        between pixels, so no tract id, pixel or cell boundary matches Rubin's.

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
        if spec.kind == "lsst":
            return cls.lsst(spec.config, spec.ra_start)
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
        if self._lsst is not None:
            return self._lsst.find_tract(ra, dec)
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
        (tract-global cell indices), the tract pixel position ``x, y``, and Rubin's ids:
        ``patch_id`` (the butler's sequential patch, ``patch_y * nx + patch_x``) and
        ``rubin_cell_x, rubin_cell_y`` (the cell's index in that patch, counted from its
        first border cell, as lsst.cell_coadds' ``cell_id``). Positions that no tract owns
        have ``tract = -1`` and the other indices -1.
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
            px, py = cx // cfg.cells_per_patch, cy // cfg.cells_per_patch
            out["patch_x"][sel] = px
            out["patch_y"][sel] = py
            out["patch_id"][sel] = py * cfg.patches_per_tract + px
            out["rubin_cell_x"][sel] = cx - (px * cfg.cells_per_patch - cfg.patch_border_cells)
            out["rubin_cell_y"][sel] = cy - (py * cfg.cells_per_patch - cfg.patch_border_cells)
            out["x"][sel] = x
            out["y"][sel] = y
        return out

    def summary(self) -> str:
        """A few lines describing the tessellation and the sizes of its levels."""
        cfg = self.config
        arcmin = cfg.pixel_scale / 60.0
        lines = [
            f"sky map: {self.spec.kind}"
            + (f" ({cfg.name})" if cfg.name else "")
            + f", {len(self)} tract(s)",
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
