"""One-line messages for the errors that reach the command line (``planarloc <command>: error: ...``)."""

from __future__ import annotations

import errno
import sqlite3

_HINTS = {
    errno.EACCES: "choose a writable location or fix its permissions",
    errno.EPERM: "choose a writable location or fix its permissions",
    errno.EROFS: "the file system is read-only; choose another location",
    errno.EISDIR: "it is a folder; give a file path",
    errno.ENOTDIR: "a part of the path is a file, not a folder; choose another path",
    errno.EEXIST: "it exists and is not a folder; choose another path",
    errno.ENOENT: "check the path",
    errno.ENOSPC: "the disk is full; free space and re-run (files written before are kept as they were)",
    errno.EFBIG: "the file is too large for this file system or limit; free space or choose another location",
}


def os_error_message(exc: OSError) -> str:
    """One line: the path(s), what went wrong, what to do."""
    where = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
    what = exc.strerror or str(exc)
    hint = _HINTS.get(exc.errno or -1, "check the path and permissions")
    return f"{where}: {what}; {hint}" if where else f"{what}; {hint}"


def sqlite_error_message(exc: sqlite3.Error) -> str:
    """One line for an SQLite error escaping the map layer."""
    text = str(exc)
    if "disk is full" in text:
        return f"the disk is full ({text}); free space and re-run the same command to resume"
    if "locked" in text or "busy" in text:
        return f"the map is busy ({text}); another process holds it, re-run when it is done"
    if "readonly" in text or "unable to open" in text:
        return f"cannot write the map ({text}); check that the map and its folder are writable"
    if isinstance(exc, sqlite3.DatabaseError) and ("malformed" in text or "not a database" in text):
        return f"the map file is damaged ({text}); run `planarloc map check MAP` and rebuild it"
    return f"map database error ({text})"
