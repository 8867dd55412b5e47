"""hloc image-pair files: one pair ``query_name db_name`` per line.

Read into ``{query_name: [db_name, ...]}`` preserving the file order of queries and of their
pairs (a repeated pair is kept once). Blank lines and ``#`` comment lines are ignored. Names
must not contain whitespace (hloc splits lines on whitespace).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

from planarloc.geometry.validation import InputError
from planarloc.io.format_error import FormatError
from planarloc.io.lines import iter_data_lines
from planarloc.io.output import write_text_atomic

FORMAT = "hloc pairs"


def read_hloc_pairs(path: Path) -> dict[str, list[str]]:
    """Read a pairs file (format in the module docstring).

    Args:
        path: the pairs file.

    Returns:
        ``{query_name: [db_name, ...]}`` in file order.

    Raises:
        FormatError: missing file, or a line without exactly two names.
    """
    path = Path(path)
    pairs: dict[str, list[str]] = {}
    seen: set[tuple[str, str]] = set()
    for lineno, tokens in iter_data_lines(path, FORMAT, "one pair 'query_name db_name' per line"):
        if len(tokens) != 2:
            raise FormatError(
                path, lineno, f"expected 2 names 'query_name db_name', found {len(tokens)} field(s)"
            )
        q, d = tokens
        if (q, d) not in seen:
            seen.add((q, d))
            pairs.setdefault(q, []).append(d)
    return pairs


def write_hloc_pairs(path: Path, pairs: Mapping[str, Iterable[str]]) -> None:
    """Write ``{query_name: [db_name, ...]}`` as a pairs file, atomically (temp file + rename).

    Raises:
        InputError: a name is empty or contains whitespace.
    """
    path = Path(path)
    lines = []
    for q, dbs in pairs.items():
        for d in dbs:
            for name in (q, d):
                if not isinstance(name, str) or not name or any(c.isspace() for c in name):
                    raise InputError(f"hloc pairs: names must be non-empty without whitespace, got {name!r}")
            lines.append(f"{q} {d}\n")
    write_text_atomic(path, lines)
