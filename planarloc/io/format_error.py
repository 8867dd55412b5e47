"""The one error type of the dataset readers.

Every reader of :mod:`planarloc.io` reports a malformed or incomplete dataset with a
:class:`FormatError`. Its message names the file, the 1-based line number (when the problem is
on a line) and what was expected versus what was found, e.g.::

    /data/seq02/poses.txt:17: expected 12 numbers (3x4 camera-to-world matrix), found 11

so that the user can open the file at that line and fix it. A missing file is reported with the
file name and what the format needs it for.
"""

from __future__ import annotations

from pathlib import Path

from planarloc.geometry.validation import InputError


class FormatError(InputError):
    """A dataset file is missing, malformed or inconsistent.

    Subclasses :class:`~planarloc.geometry.validation.InputError` (hence ``ValueError``).

    Attributes:
        path: the offending file (or directory).
        line: 1-based line number, or ``None`` if the problem concerns the whole file.
    """

    def __init__(self, path: str | Path, line: int | None, message: str) -> None:
        self.path = Path(path)
        self.line = line
        where = f"{self.path}:{line}" if line is not None else f"{self.path}"
        super().__init__(f"{where}: {message}")


def missing_file_error(path: Path, fmt: str, purpose: str) -> FormatError:
    """The error for a file the format needs but the dataset lacks.

    Args:
        path: the expected file.
        fmt: human-readable format name, e.g. ``"KITTI odometry"``.
        purpose: what the file holds, e.g. ``"one 3x4 camera-to-world pose per line"``.
    """
    return FormatError(path, None, f"file not found; the {fmt} format needs {path.name} ({purpose})")
