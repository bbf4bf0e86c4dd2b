"""The inputs of a cell as a structured array (FITS binary table, HDF5 compound dataset)."""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from cellcoadd.model.inputs import FLOAT_FIELDS, InputRecord


def _escape_ascii(text: str) -> str:
    # JSON string escapes keep any Unicode band in an ASCII-only FITS column, reversibly.
    return json.dumps(text, ensure_ascii=True)[1:-1]


def _unescape_ascii(text: str) -> str:
    return json.loads(f'"{text}"')


def inputs_to_array(records: list[InputRecord], *, ascii_only: bool) -> np.ndarray:
    """Structured array (one row per record) of the inputs of a cell.

    ``band`` and ``status`` are fixed-width byte strings: UTF-8, or JSON-escaped ASCII when
    ``ascii_only`` (FITS tables hold ASCII only).
    """
    bands = [(_escape_ascii(r.band) if ascii_only else r.band).encode("utf-8") for r in records]
    statuses = [r.status.encode("ascii") for r in records]
    band_width = max([1, *(len(b) for b in bands)])
    status_width = max([1, *(len(s) for s in statuses)])
    dtype = np.dtype(
        [
            ("visit", "<i8"),
            ("detector", "<i8"),
            ("band", f"S{band_width}"),
            ("status", f"S{status_width}"),
            *((name, "<f8") for name in FLOAT_FIELDS),
        ]
    )
    table = np.zeros(len(records), dtype=dtype)
    if records:  # column by column: a row at a time costs several times more
        table["visit"] = [record.visit for record in records]
        table["detector"] = [record.detector for record in records]
        table["band"] = bands
        table["status"] = statuses
        for name in FLOAT_FIELDS:
            table[name] = [getattr(record, name) for record in records]
    return table


def inputs_from_array(table: np.ndarray, *, ascii_only: bool) -> list[InputRecord]:
    """Validated records from a table written by :func:`inputs_to_array`.

    A float column the table lacks (``psf_flux_outside`` before format 1.3) is NaN.
    """
    names = set(table.dtype.names or ())
    records = []
    for row in table:
        band = _text(row["band"])
        records.append(
            InputRecord(
                visit=int(row["visit"]),
                detector=int(row["detector"]),
                band=_unescape_ascii(band) if ascii_only else band,
                status=_text(row["status"]),
                **{name: float(row[name]) for name in FLOAT_FIELDS if name in names},
            )
        )
    return records


def _text(value: Any) -> str:
    # Fixed-width strings come back NUL- or space-padded (bands never end in whitespace).
    if isinstance(value, (bytes, np.bytes_)):
        value = bytes(value).decode("utf-8")
    return str(value).rstrip(" \x00")
