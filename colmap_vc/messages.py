"""What `colmap-vc` tells the user when a command fails: one line each, naming the
file and what to do (used by :func:`colmap_vc.cli.run_command`)."""

from __future__ import annotations

import errno
import sqlite3
from pathlib import Path

from . import database


def database_of(cmd: object) -> Path | None:
    """The database a command works on, if it names one."""
    path = getattr(cmd, "database", None)
    return path if isinstance(path, Path) else None


def sqlite_message(exc: sqlite3.Error, cmd: object) -> str:
    """One line for a SQLite error: the database, the error and what to do."""
    db = database_of(cmd)
    where = f"{db}: " if db else ""
    text = str(exc)
    if "readonly" in text or "read-only" in text:
        hint = "make the database and its folder writable, or work on a copy"
    elif "malformed" in text or "not a database" in text or "corrupt" in text:
        hint = "the file is damaged: restore it from a backup or rebuild it with COLMAP"
    elif "locked" in text or "busy" in text:
        hint = "another process is writing it: close it and retry"
    elif "no such table" in text or "no such column" in text:
        hint = "a table is missing: was the database edited by hand? `colmap-vc strip`"
        hint += " or a fresh COLMAP database"
    elif "disk" in text or "full" in text:
        hint = "free disk space and retry"
    else:
        hint = "see --verbose"
    return f"{where}SQLite error: {text} ({hint})"


def os_message(exc: OSError) -> str:
    """One line for a file-system error: the path, the cause and what to do."""
    if exc.filename is None or str(exc.filename) in str(exc.strerror or ""):
        return str(exc)  # colmap-vc's own message, naming the file already
    name = exc.filename
    if exc.errno == errno.ENOSPC:
        return f"no space left on the device of {name}: free space and retry"
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return f"permission denied: {name} ({exc.strerror}): check its permissions"
    if exc.errno == errno.EISDIR:
        return f"{name} is a folder, a file was expected"
    if exc.errno == errno.ENOTDIR:
        return f"{name}: a part of this path is a file, a folder was expected"
    return f"{name}: {exc.strerror or exc}"


def interrupted_message(cmd: object, signal_name: str) -> str:
    """What an interrupted command leaves: its database changed or not."""
    db = database_of(cmd)
    if db is None:
        return f"interrupted by {signal_name}"
    changed = any(p.resolve() == db.resolve() for p in database.COMMITTED)
    return f"interrupted by {signal_name}: {db} " + (
        "was fully written before the interrupt"
        if changed
        else "is unchanged (colmap-vc writes it in one transaction, rolled back)"
    )
