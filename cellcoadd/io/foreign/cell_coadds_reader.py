"""Reader of the lsst.cell_coadds FITS layout (fitsio only, no LSST software needed).

A file written by :func:`~cellcoadd.io.foreign.cell_coadds_layout.write_cell_coadds` carries our
extension HDUs and reads back exactly. A file written by the LSST pipelines has none: the
patch metadata are then derived from its headers (see ``docs/format.md``), every cell of
the table becomes a cell with its used inputs, and nothing else is invented. The tract and
patch geometry comes from the sky map the file names (``SKYMAP``, e.g. ``lsst_cells_v1``)
and is checked against the file's own WCS and cell grid; the zero point of counts
(``legacy``) from the file's ``MAGZERO``, or from the caller, never a default.
"""

from __future__ import annotations

import math
import re
import warnings
from typing import Any

import fitsio
import numpy as np
from astropy.io import fits
from astropy.wcs import WCS

from cellcoadd.errors import CellCoaddFormatError, ConfigError, DamagedDataError
from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.geometry.skymap import (
    SkyMap,
    is_known_skymap,
    known_skymap_names,
    same_geometry,
)
from cellcoadd.geometry.wcs_utils import shifted_wcs
from cellcoadd.io._files.read_checks import check_path_readable, reading_errors
from cellcoadd.io._fits.checksums import verify_hdu
from cellcoadd.io._fits.paths import cfitsio_path
from cellcoadd.io.coadd.cell_records import expected_shapes, parse_cell_record
from cellcoadd.io.coadd.coadd_file import CoaddFile
from cellcoadd.io.coadd.fits_format import check_fits_path
from cellcoadd.io.coadd.format_version import MAX_METADATA_BYTES, decode_metadata, sha256_hex
from cellcoadd.io.coadd.inputs_table import inputs_from_array
from cellcoadd.io.foreign.cell_coadds_layout import (
    EXT_CELLS,
    EXT_INPUTS,
    EXT_METADATA,
    LSST_UNITS,
    MAX_VERSION,
    MIN_VERSION,
    TRACT_PIXELS_KEY,
    UNKNOWN_NAME,
    ZERO_POINT_KEY,
    CellGrid,
    grid_of,
    inner_bbox_keys,
    shape_from_quadrupole,
)
from cellcoadd.io.foreign.mask_planes import from_rubin
from cellcoadd.model.aperture_corrections import ApertureCorrections, CellApertureCorrection
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.inputs import InputRecord
from cellcoadd.model.maskbits import MAX_BITS, MaskBits
from cellcoadd.model.observations import Observations, VisitInfo
from cellcoadd.model.patch_coadd import PatchMetadata
from cellcoadd.model.units import NJY_ZERO_POINT

_VERSION = re.compile(r"^(\d+)\.(\d+)(\.\d+)?$")
#: Largest disagreement, pixels, tolerated between a file's WCS and its sky map's tract WCS
#: at the patch corners (FITS headers keep ~14 digits: ~1e-7 px).
WCS_TOLERANCE = 1e-3
_PLANE_TYPES = {"image": "f4", "mask": "i4", "variance": "f4", "psf": "f8", "maskfrac": "f4"}


def _text(value: Any) -> str:
    """A fixed-width table string, without its padding."""
    if isinstance(value, (bytes, np.bytes_)):
        value = bytes(value).decode("ascii", "replace")
    return str(value).rstrip(" \x00")


def _native(array: np.ndarray) -> np.ndarray:
    """``array`` in native byte order, bits untouched (FITS tables are big-endian)."""
    return np.ascontiguousarray(array).astype(array.dtype.newbyteorder("="), copy=False)


class CellCoaddsFile(CoaddFile):
    """An lsst.cell_coadds FITS file opened lazily: a cell's row is read on demand.

    Parameters
    ----------
    path : str
        The file.
    verify : bool
        Verify the checksums of what is read.
    legacy_zero_point : float, optional
        AB zero point of ``legacy`` (counts) pixels, for files that do not record it
        (``MAGZERO``); such files are refused without it. Refused when the file records a
        different one.
    skymap : str, optional
        Name of the sky map the file's cells are on (:func:`~cellcoadd.geometry.skymap.
        known_skymap_names`, e.g. ``DC2_cells_v1``), for a file whose ``SKYMAP`` keyword
        names none cellcoadd knows; the file's grid and WCS are checked against it. When
        the file names a known sky map, the two must have the same geometry. Unknown names
        are refused with the list of known ones.
    """

    format_name = "cell_coadds"

    def __init__(
        self,
        path: str,
        *,
        verify: bool = True,
        legacy_zero_point: float | None = None,
        skymap: str | None = None,
    ) -> None:
        check_fits_path(path)
        check_path_readable(path)
        if legacy_zero_point is not None and not math.isfinite(legacy_zero_point):
            raise ConfigError(f"legacy_zero_point must be finite, got {legacy_zero_point}")
        if skymap is not None:
            SkyMap.named(skymap)  # unknown names refused here, with the list
        self.path, self.verify = path, verify
        self.legacy_zero_point = legacy_zero_point
        self.skymap_name = skymap
        self._raw: Any = open(path, "rb")  # for the checksums; closed by close()
        self._fits: Any = None
        self._checked: set[int] = set()
        try:
            with reading_errors(path, "cannot open the FITS file"):
                self._fits = fitsio.FITS(cfitsio_path(path))
                self._numbers = {
                    hdu.get_extname().upper(): n for n, hdu in enumerate(self._fits) if n > 1
                }
            self._check_hdu_count()
            header = self._header(1)
            self.layout_version = self._check_version(header)
            self._rows, self._columns = self._read_cell_ids(header)
            self._check_inner_bbox(header)
            if EXT_METADATA in self._numbers:
                metadata, self._identities, self._inputs = self._read_extension(header)
                named = skymap and SkyMap.named(skymap).config
                if named and not same_geometry(named, metadata.skymap_config):
                    raise self._fail(
                        self._numbers[EXT_METADATA],
                        f"the file's sky map ({metadata.skymap_config.name or 'unnamed'}) "
                        f"does not have the geometry of skymap={skymap!r} given to the reader",
                    )
                self._tract_wcs: WCS | None = None
            else:
                metadata = self._derive_metadata(header)
                self._identities = {}
                self._tract_wcs = self._read_tract_wcs()
                self._inputs = self._read_used_inputs(metadata)
            self._check_columns(metadata)
        except BaseException:
            self.close()
            raise
        indices = sorted({*self._rows, *self._identities})
        super().__init__(path, metadata, indices)

    # -------------------------------------------------------------------- HDUs and checks

    def _name(self, number: int) -> str:
        if number == 0:
            return "HDU 0 (primary)"
        if number == 1:
            return "HDU 1 (cell table)"
        names = {n: name for name, n in self._numbers.items()}
        return f"HDU {number} ({names.get(number, '?')})"

    def _fail(self, number: int, problem: str) -> CellCoaddFormatError:
        return CellCoaddFormatError(self.path, f"{self._name(number)}: {problem}")

    def _hdu(self, number: int) -> Any:
        """HDU ``number``, its checksums verified once (when verifying)."""
        with reading_errors(self.path, self._name(number)):
            hdu = self._fits[number]
            if self.verify and number not in self._checked:
                verify_hdu(self._raw, hdu.get_offsets())
                self._checked.add(number)
        return hdu

    def _named(self, name: str) -> int:
        if name not in self._numbers:
            raise CellCoaddFormatError(self.path, f"HDU {name} is missing")
        return self._numbers[name]

    def _header(self, number: int) -> Any:
        if number == 1:  # the cell table: the checksum pass waits for the first cell read
            with reading_errors(self.path, self._name(1)):
                if len(self._fits) < 2 or self._fits[1].get_exttype() != "BINARY_TBL":
                    raise DamagedDataError("not a binary table", hdu=1)
                return self._fits[1].read_header()
        with reading_errors(self.path, self._name(number)):
            return self._hdu(number).read_header()

    def _table(self, number: int) -> np.ndarray | None:
        hdu = self._hdu(number)
        with reading_errors(self.path, self._name(number)):
            return hdu.read() if hdu.get_nrows() else None

    def _check_hdu_count(self) -> None:
        """A file cut at an HDU boundary is valid FITS: the count our writer states in
        CCNHDU must match (files without it, e.g. Rubin's own, are read as they are)."""
        primary = self._header(0)
        if "CCNHDU" in primary:
            stated, count = self._int(primary, "CCNHDU", 0), len(self._fits)
            if stated != count:
                raise self._fail(0, f"CCNHDU says {stated} HDUs, the file has {count} (truncated?)")

    def _int(self, header: Any, key: str, number: int = 1) -> int:
        value = header.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise self._fail(number, f"keyword {key} must be an integer, got {value!r}")
        return int(value)

    def _pair(self, header: Any, key: str) -> int:
        first, second = self._int(header, f"{key}1"), self._int(header, f"{key}2")
        if first != second:
            raise self._fail(1, f"{key}1 = {first} and {key}2 = {second}: cellcoadd needs squares")
        return first

    def _check_version(self, header: Any) -> str:
        version = str(header.get("VERSION", "")).strip()
        match = _VERSION.match(version)
        if match is None:
            raise self._fail(1, f"VERSION {version!r} is not a version number")
        number = (int(match.group(1)), int(match.group(2)))
        if not MIN_VERSION <= number < MAX_VERSION:
            raise self._fail(
                1,
                f"lsst.cell_coadds file VERSION {version} is not supported "
                f"(read: {MIN_VERSION[0]}.{MIN_VERSION[1]} <= VERSION < "
                f"{MAX_VERSION[0]}.{MAX_VERSION[1]})",
            )
        return version

    def _grid(self, header: Any) -> CellGrid:
        inner, outer = self._pair(header, "GRCELL"), self._pair(header, "OCELL")
        if inner <= 0 or outer < inner or (outer - inner) % 2:
            raise self._fail(1, f"outer cells of {outer} px do not pad {inner} px inner cells")
        first = []
        for axis in "12":
            start = self._int(header, f"GRMIN{axis}")
            if start % inner:
                raise self._fail(1, f"GRMIN{axis} = {start} is not on the {inner}-pixel cell grid")
            first.append(start // inner)
        shape = self._pair(header, "GRSHAPE")
        return CellGrid(cell_inner=inner, cell_outer=outer, shape=shape, first=(first[0], first[1]))

    def _read_cell_ids(self, header: Any) -> tuple[dict[tuple[int, int], int], dict[str, Any]]:
        """Tract-global index -> row of the cell table, and the table's column dtypes."""
        self._grid_header = self._grid(header)
        with reading_errors(self.path, self._name(1)):
            hdu = self._fits[1]
            dtype = hdu.get_rec_dtype()[0]
            columns = {name: dtype[name] for name in dtype.names}
            if "cell_id" not in columns:
                raise DamagedDataError("column 'cell_id' is missing", hdu=1)
            ids: Any = np.zeros((0, 2), dtype=int)
            if hdu.get_nrows():
                ids = hdu.read_column("cell_id")
            ids = np.asarray(ids).reshape(-1, 2)
        if len(ids) == 0:
            raise self._fail(
                1,
                "the cell table has no rows: an lsst.cell_coadds file holds at least one cell "
                "(Rubin's reader cannot read one without; Rubin's builder writes none)",
            )
        rows: dict[tuple[int, int], int] = {}
        grid = self._grid_header
        for row, (i, j) in enumerate(ids.tolist()):
            if not (0 <= i < grid.shape and 0 <= j < grid.shape):
                raise self._fail(1, f"row {row}: cell_id ({i}, {j}) is outside the grid")
            key = grid.global_index((int(i), int(j)))
            if key in rows:
                raise self._fail(1, f"cell_id ({i}, {j}) appears in rows {rows[key]} and {row}")
            rows[key] = row
        return rows, columns

    def _check_columns(self, meta: PatchMetadata) -> None:
        side, psf = meta.cell_outer, meta.psf_size
        wanted = {name: (kind, (side, side)) for name, kind in _PLANE_TYPES.items()}
        wanted["psf"] = ("f8", (psf, psf))
        wanted.update({f"noise_{n:02}": ("f4", (side, side)) for n in range(meta.n_noise)})
        for name, (kind, shape) in wanted.items():
            found = self._columns.get(name)
            if found is None:
                if name == "maskfrac":
                    continue  # optional: read as zeros
                raise self._fail(1, f"column {name!r} is missing")
            base, dims = (found.base, found.shape) if found.subdtype else (found, ())
            if base.kind + str(base.itemsize) != kind or dims != shape:
                raise self._fail(1, f"column {name!r} is {base}{dims}, expected {kind}{shape}")

    # -------------------------------------------------------------------- our extension

    def _read_extension(
        self, header: Any
    ) -> tuple[PatchMetadata, dict[tuple[int, int], dict[str, Any]], dict[Any, list[InputRecord]]]:
        number = self._named(EXT_METADATA)
        hdu = self._hdu(number)
        with reading_errors(self.path, self._name(number)):
            dims = hdu.get_dims()
            if len(dims) != 1 or not 0 < dims[0] <= MAX_METADATA_BYTES:
                raise DamagedDataError(f"dimensions {dims}", hdu=number)
            payload = hdu.read().astype(np.uint8, copy=False).tobytes()
            keys = hdu.read_header()
            if keys.get("METASHA") != sha256_hex(payload):
                raise DamagedDataError("metadata SHA-256 mismatch: corrupted metadata", hdu=number)
            metadata = decode_metadata(self.path, payload, str(keys.get("CCVERS")))
        if grid_of(metadata) != self._grid_header or (
            self._int(header, "TRACT"),
            self._int(header, "PATCH_X"),
            self._int(header, "PATCH_Y"),
        ) != (metadata.tract, *metadata.patch):
            raise self._fail(number, "the cellcoadd metadata disagree with the cell table header")
        number = self._named(EXT_CELLS)
        identities: dict[tuple[int, int], dict[str, Any]] = {}
        stored = {row: key for key, row in self._rows.items()}
        table = self._table(number)
        with reading_errors(self.path, self._name(number)):
            for entry in [] if table is None else table:
                key = (int(entry["CELL_X"]), int(entry["CELL_Y"]))
                identity = parse_cell_record(entry["CELL"])
                row = int(entry["ROW"])
                if identity["index"] != key or stored.get(row, key if row < 0 else None) != key:
                    raise DamagedDataError(
                        f"cell {key} (row {row}) does not match the cell table", cell=key
                    )
                identities[key] = identity
            if not set(self._rows) <= set(identities):
                raise DamagedDataError("the cell table has cells this table does not list")
        number = self._named(EXT_INPUTS)
        inputs: dict[Any, list[InputRecord]] = {}
        table = self._table(number)
        with reading_errors(self.path, self._name(number)):
            for key in identities:
                if table is None:
                    break
                selected = (table["CELL_X"] == key[0]) & (table["CELL_Y"] == key[1])
                inputs[key] = inputs_from_array(table[selected], ascii_only=True)
        return metadata, identities, inputs

    # -------------------------------------------------------------------- LSST-only files

    def _read_tract_wcs(self) -> WCS:
        header = self._header(0)
        with reading_errors(self.path, f"{self._name(0)}: the WCS"), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # astropy's notes on fixed-up cards
            text = "\n".join(record["card_string"] for record in header.records())
            wcs = WCS(fits.Header.fromstring(text, sep="\n"), naxis=2)
        if not wcs.has_celestial:
            raise self._fail(0, "no celestial WCS")
        if wcs.wcs.has_cd():  # afw writes CD; our WCS records hold PC and CDELT
            cd = wcs.wcs.cd.copy()
            del wcs.wcs.cd
            wcs.wcs.pc, wcs.wcs.cdelt = cd, [1.0, 1.0]
            wcs.wcs.set()
        return wcs

    def _mask_bits(self) -> MaskBits:
        number = self._named("MASKDEF")
        table = self._table(number)
        bits: dict[str, int] = {}
        for entry in [] if table is None else table:
            name, bit = str(entry["MASK_NAME"]).strip(), int(entry["BIT_VALUE"])
            if not 0 <= bit < MAX_BITS:
                raise self._fail(number, f"mask plane {name!r} is bit {bit}; cellcoadd has 0..30")
            bits[name] = bit
        bits = from_rubin(bits, "afw")  # our names for Rubin's (afw) plane names
        if "NO_DATA" not in bits:
            bits["NO_DATA"] = min(set(range(MAX_BITS)) - set(bits.values()))
        with reading_errors(self.path, self._name(number)):
            return MaskBits(bits=bits)

    def _zero_point(self, header: Any) -> tuple[str, float]:
        """Our unit and zero point for ``TUNIT2`` (and ``MAGZERO``, or the caller's)."""
        units = str(header.get("TUNIT2", "")).strip()
        if units not in LSST_UNITS:
            raise self._fail(1, f"TUNIT2 = {units!r}, expected one of {', '.join(LSST_UNITS)}")
        if units == "chi":
            raise self._fail(1, "TUNIT2 = 'chi': cellcoadd holds flux coadds (nJy or counts)")
        if units == "nJy":
            return "nJy", NJY_ZERO_POINT
        stored = header.get(ZERO_POINT_KEY)
        if stored is None:
            if self.legacy_zero_point is None:
                raise self._fail(
                    1,
                    f"TUNIT2 = 'legacy' (counts) and no {ZERO_POINT_KEY}: the zero point of the "
                    "pixels is not recorded (lsst.cell_coadds says 'typically 27'); pass it "
                    "explicitly, e.g. cellcoadd.read(path, legacy_zero_point=27.0) (also "
                    "cellcoadd.open), or --legacy-zero-point 27 on the command line",
                )
            return "count", float(self.legacy_zero_point)
        if isinstance(stored, bool) or not isinstance(stored, (int, float, np.number)):
            raise self._fail(1, f"{ZERO_POINT_KEY} = {stored!r} is not a number")
        if not math.isfinite(float(stored)):
            raise self._fail(1, f"{ZERO_POINT_KEY} = {stored!r} is not finite")
        given = self.legacy_zero_point
        if given is not None and given != float(stored):
            raise self._fail(
                1, f"{ZERO_POINT_KEY} = {stored} but legacy_zero_point = {given} was given"
            )
        return "count", float(stored)

    def _patch_cells(self, header: Any) -> tuple[int, int]:
        """``(cells_per_patch, patch_border_cells)`` from the grid and the patch index."""
        grid = self._grid_header
        px, py = self._int(header, "PATCH_X"), self._int(header, "PATCH_Y")
        # GRMIN = (patch * cells_per_patch - border) * cell_inner, GRSHAPE = cells + 2 border
        borders = set()
        for patch, first in ((px, grid.first[0]), (py, grid.first[1])):
            border, rest = divmod(patch * grid.shape - first, 2 * patch + 1)
            borders.add(border if rest == 0 and 0 <= 2 * border < grid.shape else -1)
        border = borders.pop()
        if borders or border < 0:
            raise self._fail(1, "GRMIN/GRSHAPE do not place the patch's cells on a tract grid")
        return grid.shape - 2 * border, border

    def _declared_geometry(
        self, header: Any, wcs: WCS, name: str
    ) -> tuple[SkyMapConfig, tuple[float, float]]:
        """Sky map configuration and tract centre from a sky map we know by name, checked
        against the file's cell grid and WCS."""
        skymap = SkyMap.named(name)
        config = skymap.config
        tract_id = self._int(header, "TRACT")
        if not 0 <= tract_id < len(skymap):
            raise self._fail(1, f"TRACT = {tract_id} is not a tract of {name} ({len(skymap)})")
        tract = skymap[tract_id]
        grid = self._grid_header
        per_patch, border = self._patch_cells(header)
        found = (grid.cell_inner, grid.cell_outer, per_patch, border)
        wanted = (
            config.cell_inner,
            config.cell_outer,
            config.cells_per_patch,
            config.patch_border_cells,
        )
        if found != wanted:
            raise self._fail(
                1,
                f"SKYMAP = {name!r} has cells of {wanted[0]} px inner, {wanted[1]} px outer, "
                f"{wanted[2]} per patch with {wanted[3]} border cell(s), but the cell table "
                f"has {found[0]}, {found[1]}, {found[2]} and {found[3]}",
            )
        patch = (self._int(header, "PATCH_X"), self._int(header, "PATCH_Y"))
        n = config.patches_per_tract
        if not all(0 <= p < n for p in patch):
            raise self._fail(1, f"patch {patch} is outside {name}'s {n} x {n} patches")
        box = tract.patch(*patch).outer_bbox
        xs = np.array([box.x_start, box.x_stop - 1, box.x_start, box.x_stop - 1], dtype=float)
        ys = np.array([box.y_start, box.y_start, box.y_stop - 1, box.y_stop - 1], dtype=float)
        with reading_errors(self.path, f"{self._name(0)}: the WCS"):
            ra, dec = wcs.all_pix2world(xs, ys, 0)
            x, y = tract.wcs.all_world2pix(ra, dec, 0)
        off = float(np.max(np.hypot(x - xs, y - ys)))
        if not off <= WCS_TOLERANCE:
            raise self._fail(
                0,
                f"the WCS disagrees with SKYMAP = {name!r} tract {tract_id}: the patch corners "
                f"are {off:.4g} px from where the sky map puts them (tract centre "
                f"{tract.center}, tangent pixel {config.tangent_pixel}; the file has CRVAL "
                f"{tuple(float(v) for v in wcs.wcs.crval)}, CRPIX "
                f"{tuple(float(v) for v in wcs.wcs.crpix)})",
            )
        return config, tract.center

    def _wcs_geometry(
        self, header: Any, wcs: WCS, name: str
    ) -> tuple[SkyMapConfig, tuple[float, float]]:
        """Sky map configuration and tract centre from the file's WCS and keywords alone,
        for a sky map we do not know by name (ours: ``SKYMAP = 'cellcoadd'``)."""
        grid = self._grid_header
        per_patch, border = self._patch_cells(header)
        scale = float(np.sqrt(abs(np.linalg.det(wcs.pixel_scale_matrix)))) * 3600.0
        scale = float(f"{scale:.12g}")  # the sky map's nominal value, not its rounding
        crpix = wcs.wcs.crpix - 1.0  # 0-based tangent pixel
        if crpix[0] != crpix[1]:
            raise self._fail(0, f"CRPIX {tuple(wcs.wcs.crpix)}: not on the tract diagonal")
        if TRACT_PIXELS_KEY in header:
            tract_pixels = self._int(header, TRACT_PIXELS_KEY)
        elif crpix[0] != round(crpix[0]):  # our own tracts: tangent point at the box centre
            tract_pixels = round(2.0 * crpix[0] + 1.0)
        else:
            known = ", ".join(known_skymap_names())
            raise self._fail(
                1,
                f"SKYMAP = {name!r} is not a sky map cellcoadd knows ({known}) and the file "
                f"gives no {TRACT_PIXELS_KEY}: the tract size cannot be derived",
            )
        patch_inner = per_patch * grid.cell_inner
        if tract_pixels <= 0 or tract_pixels % patch_inner:
            raise self._fail(
                1, f"a tract of {tract_pixels} px is not a whole number of {patch_inner}-px patches"
            )
        centred = crpix[0] == (tract_pixels - 1) / 2.0
        if not centred and (crpix[0] != round(crpix[0]) or not 0 <= crpix[0] < tract_pixels):
            raise self._fail(0, f"CRPIX {tuple(wcs.wcs.crpix)} is not a tangent pixel")
        with reading_errors(self.path, f"{self._name(1)}: deriving the sky map"):
            config = SkyMapConfig(
                pixel_scale=scale,
                cell_inner=grid.cell_inner,
                cell_border=(grid.cell_outer - grid.cell_inner) // 2,
                cells_per_patch=per_patch,
                patch_border_cells=border,
                patches_per_tract=tract_pixels // patch_inner,
                tangent_pixel=None if centred else round(crpix[0]),
                name=None if name in ("", UNKNOWN_NAME) else name,
            )
        return config, (float(wcs.wcs.crval[0]) % 360.0, float(wcs.wcs.crval[1]))

    def _observations(self, header: Any) -> Observations | None:
        instrument = str(header.get("INSTRUME", "")).strip()
        if instrument in ("", UNKNOWN_NAME):
            return None
        number = self._named("VISIT")
        table = self._table(number)
        with reading_errors(self.path, self._name(number)):
            visits = [
                VisitInfo(
                    visit=int(row["visit"]),
                    physical_filter=_text(row["physical_filter"]),
                    day_obs=int(row["day_obs"]),
                )
                for row in ([] if table is None else table)
            ]
            return Observations(instrument=instrument, visits=tuple(visits))

    def _derive_metadata(self, header: Any) -> PatchMetadata:
        """Patch metadata of a file without our extension, from its headers and MASKDEF."""
        px, py = self._int(header, "PATCH_X"), self._int(header, "PATCH_Y")
        unit, zero_point = self._zero_point(header)
        wcs = self._read_tract_wcs()
        name = str(header.get("SKYMAP", "")).strip()
        if self.skymap_name is not None:
            self._check_named_skymap(name)
            config, center = self._declared_geometry(header, wcs, self.skymap_name)
        elif is_known_skymap(name):
            config, center = self._declared_geometry(header, wcs, name)
        else:
            config, center = self._wcs_geometry(header, wcs, name)
        with reading_errors(self.path, f"{self._name(1)}: deriving the patch metadata"):
            return PatchMetadata(
                skymap_config=config,
                tract=self._int(header, "TRACT"),
                tract_center=center,
                patch=(px, py),
                band=str(header.get("FILTER", "")).strip(),
                units=unit,
                zero_point=zero_point,
                mask_bits=self._mask_bits(),
                build_config=BuildConfig(
                    n_noise=self._int(header, "NNOISE") if "NNOISE" in header else 0,
                    psf_size=self._pair(header, "PSFSIZE"),
                    units=unit,
                    zero_point=zero_point,
                ),
                software_version=f"lsst.cell_coadds (file VERSION {self.layout_version})",
                observations=self._observations(header),
                aperture_corrections=self._aperture_corrections(),
            )

    def _check_named_skymap(self, name: str) -> None:
        """The caller's sky map (``skymap=``) must have the geometry of the one the file
        names, when the file names one cellcoadd knows."""
        assert self.skymap_name is not None
        if is_known_skymap(name) and not same_geometry(
            SkyMap.named(name).config, SkyMap.named(self.skymap_name).config
        ):
            raise self._fail(
                1,
                f"SKYMAP = {name!r}, whose geometry is not that of skymap="
                f"{self.skymap_name!r} given to the reader",
            )

    def _check_inner_bbox(self, header: Any) -> None:
        """``INBBOX`` must lie in the grid box grown by the cell border (Rubin's reader
        refuses anything else); files before the border was added say the grid box."""
        keys = ("INBBOX11", "INBBOX12", "INBBOX21", "INBBOX22")
        if not all(key in header for key in keys):
            return
        box = [self._int(header, key) for key in keys]
        grid = self._grid_header
        widest = inner_bbox_keys(grid)
        if not (
            widest[0] <= box[0] <= box[2] <= widest[2]
            and widest[1] <= box[1] <= box[3] <= widest[3]
        ):
            raise self._fail(
                1,
                f"INBBOX ({box[0]}, {box[1]}) ... ({box[2]}, {box[3]}) is not inside the cell "
                f"grid's box with its border ({widest[0]}, {widest[1]}) ... "
                f"({widest[2]}, {widest[3]})",
            )

    def _aperture_corrections(self) -> ApertureCorrections | None:
        """Every column of ``APCORR`` (None without the HDU or without an algorithm
        column, as our own files without corrections have)."""
        if "APCORR" not in self._numbers:
            return None
        number = self._numbers["APCORR"]
        hdu = self._hdu(number)
        with reading_errors(self.path, self._name(number)):
            dtype = hdu.get_rec_dtype()[0]
            names = list(dtype.names or ())
            if "x" not in names or "y" not in names:
                raise DamagedDataError("columns 'x' and 'y' are missing", hdu=number)
            algorithms = [name for name in names if name not in ("x", "y")]
            for name in algorithms:
                if dtype[name].kind not in "fiu" or dtype[name].shape:
                    raise DamagedDataError(f"column {name!r} is {dtype[name]}, not a number")
            if not algorithms:
                return None
            table = hdu.read() if hdu.get_nrows() else np.zeros(0, dtype=dtype)
            cells = []
            grid = self._grid_header
            for row, entry in enumerate(table):
                i, j = int(entry["x"]), int(entry["y"])
                if not (0 <= i < grid.shape and 0 <= j < grid.shape):
                    raise DamagedDataError(f"row {row}: cell ({i}, {j}) is outside the grid")
                values = [float(entry[name]) for name in algorithms]
                cells.append(
                    CellApertureCorrection(
                        index=grid.global_index((i, j)),
                        values=tuple(v if math.isfinite(v) else None for v in values),
                    )
                )
            return ApertureCorrections(algorithms=tuple(algorithms), cells=tuple(cells))

    def _read_used_inputs(self, meta: PatchMetadata) -> dict[Any, list[InputRecord]]:
        number = self._named("CELL")
        table = self._table(number)
        scale = meta.skymap_config.pixel_scale
        zero_point = math.nan  # the exposures' own zero points are not recorded
        inputs: dict[Any, list[InputRecord]] = {}
        for row, entry in enumerate([] if table is None else table):
            with reading_errors(self.path, f"{self._name(number)} row {row}"):
                key = self._grid_header.global_index((int(entry["cell_x"]), int(entry["cell_y"])))
                shape = shape_from_quadrupole(
                    float(entry["psf_shape_ixx"]),
                    float(entry["psf_shape_iyy"]),
                    float(entry["psf_shape_ixy"]),
                    bool(entry["psf_shape_flag"]),
                    scale,
                )
                record = InputRecord(
                    visit=int(entry["visit"]),
                    detector=int(entry["detector"]),
                    band=meta.band,
                    weight=float(entry["weight"]),
                    status="used",
                    overlap_fraction=float(entry["overlap_fraction"]),
                    zero_point=zero_point,
                    **shape,
                )
                if key not in self._rows:
                    raise DamagedDataError(f"cell {key} has no row in the cell table", cell=key)
                inputs.setdefault(key, []).append(record)
        return inputs

    # -------------------------------------------------------------------- cells

    def _identity(self, key: tuple[int, int]) -> dict[str, Any]:
        if key in self._identities:
            return self._identities[key]
        inner, outer = self.metadata.cell_boxes(key)
        assert self._tract_wcs is not None
        wcs = shifted_wcs(self._tract_wcs, outer.x_start, outer.y_start)
        return {
            "tract": self.metadata.tract,
            "index": key,
            "inner_bbox": inner,
            "outer_bbox": outer,
            "wcs": wcs,
        }

    def read_cell(self, index: tuple[int, int]) -> CellCoadd:
        key = self._check_index(index)
        identity = self._identity(key)
        meta = self.metadata
        inputs = self._inputs.get(key, [])
        row = self._rows.get(key)
        if row is None:  # an empty cell, absent from the grid
            with reading_errors(self.path, f"{self._name(self._named(EXT_CELLS))} cell {key}"):
                return CellCoadd.empty(
                    **identity,
                    n_noise=meta.n_noise,
                    psf_size=meta.psf_size,
                    inputs=inputs,
                    mask_bits=meta.mask_bits,
                    common=meta.cell_common,
                )
        hdu = self._hdu(1)
        where = f"{self._name(1)} row {row} (cell {key})"
        with reading_errors(self.path, where):
            data = hdu.read(rows=[row])[0]
            shapes = expected_shapes(meta, identity["outer_bbox"])
            if shapes["image"] != (meta.cell_outer, meta.cell_outer):
                raise DamagedDataError(f"the cell's outer box is {shapes['image']}", cell=key)
            mfrac = (
                _native(data["maskfrac"])
                if "maskfrac" in self._columns
                else np.zeros(shapes["mfrac"], dtype=np.float32)
            )
            noise = [_native(data[f"noise_{n:02}"]) for n in range(meta.n_noise)]
            mask = _native(data["mask"])
            unknown = meta.mask_bits.unknown_bits(mask)
            if unknown:
                raise DamagedDataError(
                    f"mask has bits {unknown:#x} that MASKDEF does not name", cell=key
                )
            return CellCoadd(
                image=_native(data["image"]),
                mask=mask,
                variance=_native(data["variance"]),
                noise=np.stack(noise) if noise else np.zeros(shapes["noise"], np.float32),
                mfrac=mfrac,
                psf=_native(data["psf"]),
                inputs=inputs,
                **identity,
                common=meta.cell_common,
            )

    def read_cell_inputs(self, index: tuple[int, int]) -> list[InputRecord]:
        return list(self._inputs.get(self._check_index(index), []))

    def close(self) -> None:
        fits = getattr(self, "_fits", None)
        if fits is not None:
            fits.close()
            self._fits = None
        raw = getattr(self, "_raw", None)
        if raw is not None:
            raw.close()
            self._raw = None
