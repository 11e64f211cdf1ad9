"""Opening a COLMAP database safely: read-only reads, one-transaction writes.

Reads run under ``PRAGMA query_only`` (read-only ``mode=ro`` where the file or its
folder is not writable, ``immutable=1`` in a read-only folder); a write is refused
before any work when the file or folder is read-only or the file is damaged, and
runs in one ``BEGIN IMMEDIATE`` transaction (docs/database.md, guarantees).
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
from collections.abc import Iterator
from os import PathLike
from pathlib import Path

from colmap_vc import database_schema as sch
from colmap_vc import database_write as dbw
from colmap_vc.database_schema import Schema

BUSY_TIMEOUT_S = 0.5  # fail fast (RuntimeError) when another process writes
COMMITTED: list[Path] = []
"""Databases this process changed (committed transactions), for the CLI's report
after an interrupt: any other database is as it was."""


@contextlib.contextmanager
def connect(
    db_path: str | PathLike[str], *, write: bool
) -> Iterator[tuple[sqlite3.Connection, Schema]]:
    """Open an existing COLMAP database (never creates one) and detect its schema."""
    path = Path(db_path)
    if not path.is_file():
        raise FileNotFoundError(f"COLMAP database not found: {path}")
    if write:
        require_writable(path)
    # Reads open read-write with query_only where the user may write: SQLite's
    # last read-write connection removes the -wal/-shm files of a WAL database on
    # close, a read-only one leaves them behind. query_only refuses every write.
    mode = "rw" if write or is_writable(path) else "ro"
    # A read-only folder: SQLite cannot create the -shm file a WAL database needs,
    # and nobody can write the database without creating its -wal file there, so
    # an existing -wal is the only sign of a writer.
    if (
        not write
        and not os.access(path.parent, os.W_OK)
        and not Path(f"{path}-wal").exists()
    ):
        mode += "&immutable=1"
    conn = sqlite3.connect(
        f"{path.resolve().as_uri()}?mode={mode}",
        uri=True,
        timeout=BUSY_TIMEOUT_S,
        isolation_level=None,  # transactions are explicit, see transaction()
    )
    try:
        if not write:
            conn.execute("PRAGMA query_only = ON")
        try:
            tables = sch.table_names(conn)
        except sqlite3.DatabaseError as error:
            if "locked" in str(error):
                raise RuntimeError(f"{path} is locked: {error}") from error
            raise ValueError(f"{path} is not a SQLite database: {error}") from error
        missing = [t for t in sch.COLMAP_TABLES if t not in tables]
        if missing:
            raise ValueError(f"{path} is not a COLMAP database: no tables {missing}")
        try:
            yield conn, sch.detect_schema(tables)
        except sqlite3.OperationalError as error:
            if "locked" in str(error) or "busy" in str(error):
                raise RuntimeError(f"{path} is locked: {error}") from error
            raise
    finally:
        conn.close()


def is_writable(path: Path) -> bool:
    return os.access(path, os.W_OK) and os.access(path.parent, os.W_OK)


def require_writable(db_path: str | PathLike[str]) -> None:
    """Raise PermissionError unless the database and its folder (SQLite writes its
    rollback journal there) are writable by this process."""
    path = Path(db_path)
    for what, target in (("database", path), ("folder of the database", path.parent)):
        if not os.access(target, os.W_OK):
            raise PermissionError(
                f"the {what} {target} is read-only: make it writable (chmod u+w) or "
                "work on a copy; nothing was changed"
            )


def check_before_write(db_path: str | PathLike[str]) -> None:
    """Everything that would make a later VC write fail, checked now (only reads).

    ``augment`` calls this before it computes VCs, so a read-only, damaged or
    user-changed database is refused in a second, not after minutes of work.
    Raises PermissionError or ValueError (see :func:`write_virtual_correspondences`).
    """
    path = Path(db_path)
    require_writable(path)
    with connect(path, write=False) as (conn, _):
        require_intact(conn, path)
        if "colmap_vc_state" in sch.vc_table_names(conn):
            try:
                dbw.require_strippable(conn)
            except ValueError as error:
                raise ValueError(
                    f"{path}: cannot replace the earlier VCs: {error}"
                ) from error


@contextlib.contextmanager
def transaction(conn: sqlite3.Connection, path: Path) -> Iterator[None]:
    """One write transaction: all or nothing, also if the process dies inside it."""
    try:
        conn.execute("BEGIN IMMEDIATE")  # take the write lock now, not mid-way
    except sqlite3.OperationalError as error:
        raise RuntimeError(
            f"{path} is locked by another connection ({error}): close the other "
            "COLMAP process and retry"
        ) from error
    try:
        yield
        conn.execute("COMMIT")
        COMMITTED.append(path)
    except BaseException:
        if conn.in_transaction:
            conn.execute("ROLLBACK")
        raise


def require_intact(conn: sqlite3.Connection, path: Path) -> None:
    """Refuse to write into a damaged file (SQLite's quick_check reads every page)."""
    try:
        problems = [r[0] for r in conn.execute("PRAGMA quick_check(3)")]
    except sqlite3.DatabaseError as error:
        problems = [str(error)]
    if problems != ["ok"]:
        raise ValueError(
            f"{path} is damaged ({'; '.join(problems)}): restore it from a backup or "
            "rebuild it with COLMAP; colmap-vc did not change it"
        )


def snapshot(db_path: str | PathLike[str], copy_path: str | PathLike[str]) -> Path:
    """A consistent copy of the database at ``copy_path``; the original is only read.

    pycolmap's mappers open their database read-write and migrate it to their
    schema; ``map`` gives them this copy so the user's file is never written.
    """
    path, copy = Path(db_path), Path(copy_path)
    with connect(path, write=False) as (conn, _):
        target = sqlite3.connect(copy)
        try:
            conn.backup(target)
        except sqlite3.OperationalError as error:
            raise RuntimeError(f"cannot copy {path} to {copy}: {error}") from error
        finally:
            target.close()
    return copy
