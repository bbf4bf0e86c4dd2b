"""The zero point of an LSST ``ExposureF`` file's persisted ``PhotoCalib``.

Current LSST Science Pipelines files (``calexp``, ``visit_image``) no longer write
``FLUXMAG0``: the photometric calibration is a ``PhotoCalib`` object in the file's afw
archive. The primary header gives ``AR_HDU``, the 1-based number of the archive's index
HDU, and ``PHOTOCALIB_ID``, the object's id in that index. The index is a binary table with
one row per catalog of each object (``id``, ``cat.archive``: the catalog's HDU counted from
the index HDU, ``row0``, ``nrows``); the ``PhotoCalib`` catalog has the columns
``calibrationMean`` (nJy per count) and ``calibrationErr``.

A count is ``calibrationMean`` nJy, so the zero point (AB mag of one count) is
``31.4 - 2.5 log10(calibrationMean)``. A spatially varying calibration is represented by
its mean: cellcoadd scales each exposure by one number.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from cellcoadd.io.exposures.mef_file import MefFile
from cellcoadd.model.units import NJY_ZERO_POINT

#: Primary-header keywords of the archive index HDU (1-based) and of the PhotoCalib's id.
ARCHIVE_HDU_KEY = "AR_HDU"
PHOTOCALIB_ID_KEY = "PHOTOCALIB_ID"


def zero_point_from_calibration(calibration_mean: float) -> float | None:
    """The zero point, mag, of ``calibration_mean`` nJy per count; None unless positive.

    >>> zero_point_from_calibration(1.0) == NJY_ZERO_POINT  # pixels in nJy: 31.4
    True
    >>> round(zero_point_from_calibration(10 ** (-0.4 * (27.0 - NJY_ZERO_POINT))), 12)
    27.0
    """
    if not (math.isfinite(calibration_mean) and calibration_mean > 0):
        return None
    return NJY_ZERO_POINT - 2.5 * math.log10(calibration_mean)


def photocalib_zero_point(mef: MefFile, id_key: str = PHOTOCALIB_ID_KEY) -> float | None:
    """The zero point of the ``PhotoCalib`` in ``mef``'s afw archive, or None without one.

    ``id_key`` is the primary-header keyword of the object's id.

    Raises
    ------
    CellCoaddFormatError
        When the primary header points at an archive or an object that is not there, or
        the catalog has no usable ``calibrationMean`` (naming the file and the HDU).
    """
    primary = mef.header(0)
    if id_key not in primary:
        return None
    object_id = _integer(mef, primary, id_key)
    index_hdu = _integer(mef, primary, ARCHIVE_HDU_KEY) - 1
    count = len(mef.fits)
    if not 0 < index_hdu < count:
        raise mef.fail(0, f"{ARCHIVE_HDU_KEY} = {index_hdu + 1} is not an HDU of the file")
    index = _table(mef, index_hdu, ("id", "cat.archive", "row0", "nrows"))
    rows = index[index["id"] == object_id]
    if len(rows) == 0:
        raise mef.fail(index_hdu, f"the archive has no object {id_key}={object_id}")
    for row in rows:  # the object's catalogs: the one with the calibration
        hdu = index_hdu + int(row["cat.archive"])
        if not index_hdu < hdu < count:
            continue
        names = {name.lower() for name in _column_names(mef, hdu)}
        if "calibrationmean" not in names:
            continue
        start = int(row["row0"])
        catalog = _table(mef, hdu, ("calibrationMean",), rows=range(start, start + 1))
        value = float(catalog["calibrationMean"][0])
        zero_point = zero_point_from_calibration(value)
        if zero_point is None:
            raise mef.fail(hdu, f"PhotoCalib calibrationMean = {value} is not a positive number")
        return zero_point
    raise mef.fail(index_hdu, f"no PhotoCalib catalog (calibrationMean) for {id_key}={object_id}")


def _integer(mef: MefFile, header: Any, key: str) -> int:
    value = header.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise mef.fail(0, f"{key} = {value!r} is not an integer")
    return int(value)


def _column_names(mef: MefFile, hdu: int) -> list[str]:
    try:
        if mef.fits[hdu].get_exttype() != "BINARY_TBL":
            return []
        return list(mef.fits[hdu].get_colnames())
    except (OSError, ValueError) as err:
        raise mef.fail(hdu, f"cannot read the archive table ({err})") from None


def _table(
    mef: MefFile, hdu: int, columns: tuple[str, ...], rows: range | None = None
) -> np.ndarray:
    names = _column_names(mef, hdu)
    lower = {name.lower(): name for name in names}
    missing = [c for c in columns if c.lower() not in lower]
    if missing:
        raise mef.fail(hdu, f"the archive table lacks the columns {missing}")
    try:
        data = mef.fits[hdu].read(
            columns=[lower[c.lower()] for c in columns],
            rows=None if rows is None else list(rows),
        )
    except (OSError, ValueError, IndexError) as err:
        raise mef.fail(hdu, f"cannot read the archive table ({err})") from None
    renamed = np.empty(len(data), dtype=[(c, data.dtype[lower[c.lower()]]) for c in columns])
    for column in columns:
        renamed[column] = data[lower[column.lower()]]
    return renamed
