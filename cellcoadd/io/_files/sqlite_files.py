"""Our SQLite files (the exposure index, the run ledger): opened only when they say they
are ours, so that a foreign database given by mistake is refused unmodified.

Each kind of file has its own ``PRAGMA application_id`` and keeps its schema version in
``PRAGMA user_version`` (both in the database header, readable before any table). A new,
empty file is given both and its tables; an existing one must carry the kind's
application id and version, or it is refused before anything is written to it.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

from cellcoadd.errors import CellCoaddFormatError


def open_own_database(
    path: str,
    *,
    application_id: int,
    version: int,
    schema: str,
    what: str,
    readonly: bool = False,
    older: str = "",
) -> sqlite3.Connection:
    """A connection to our SQLite file ``path`` (already through the path gate).

    Parameters
    ----------
    path : str
        The file (created empty by a writer when missing).
    application_id, version : int
        What ``PRAGMA application_id`` and ``PRAGMA user_version`` must say.
    schema : str
        The tables (``CREATE ... IF NOT EXISTS``), created in a new file.
    what : str
        What the file is, for messages ("exposure index").
    readonly : bool
        Open for reading only (the file must exist).
    older : str
        What to do with a file of another version (appended to the message).

    Raises
    ------
    CellCoaddFormatError
        When the file is not a SQLite database, is another application's (or an older
        layout's) database, or has another schema version; nothing is written to it.
    """
    try:
        if readonly:
            db = sqlite3.connect(f"{Path(path).as_uri()}?mode=ro", uri=True, timeout=60.0)
        else:
            db = sqlite3.connect(path, timeout=60.0)
        (found_id,) = db.execute("PRAGMA application_id").fetchone()
        (found_version,) = db.execute("PRAGMA user_version").fetchone()
        (tables,) = db.execute("SELECT COUNT(*) FROM sqlite_master").fetchone()
    except sqlite3.DatabaseError as err:
        raise CellCoaddFormatError(path, f"not a {what} ({err})") from None
    if found_id == 0 and tables == 0 and not readonly:
        try:
            with db:
                db.execute(f"PRAGMA application_id = {int(application_id)}")
                db.execute(f"PRAGMA user_version = {int(version)}")
                db.executescript(schema)
        except sqlite3.DatabaseError as err:
            db.close()
            raise CellCoaddFormatError(path, f"cannot create a {what} ({err})") from None
        return db
    if found_id != application_id:
        db.close()
        hint = f" (an older {what}?{' ' + older if older else ''})" if tables else ""
        raise CellCoaddFormatError(
            path,
            f"not a {what}: another SQLite database (application id {found_id:#x}, "
            f"{tables} schema objects){hint}; it was left unmodified",
        )
    if found_version != version:
        db.close()
        raise CellCoaddFormatError(
            path,
            f"{what} schema version {found_version}, this library reads version {version}"
            + (f": {older}" if older else ""),
        )
    return db
