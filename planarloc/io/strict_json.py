"""Strict JSON for every file and response planarloc writes (issue 32).

Python's ``json`` writes ``NaN`` and ``Infinity`` by default, which is not JSON: strict parsers
(JavaScript's ``JSON.parse``, Go, Rust's serde_json) reject the whole document. planarloc's
records carry non-finite numbers where a value is absent (the std of a failed fix is ``inf``, an
error without a truth is ``nan``); in a written document those are ``null``.

:func:`to_jsonable` converts a record (dicts, lists, tuples, numpy scalars and arrays, floats) to
plain JSON types with every non-finite float as ``None``; :func:`dumps` writes it with
``allow_nan=False``, so a non-finite number that slipped through is an error here, not in the
reader's parser.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

import numpy as np


def to_jsonable(value: Any) -> Any:
    """``value`` with plain JSON types: non-finite floats → None, numpy scalars → Python numbers,
    arrays and tuples → lists, mapping keys → strings. Other objects are returned as they are
    (``json`` raises on them, as it should)."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    return value


def dumps(value: Any, **kwargs: Any) -> str:
    """Strict JSON text of ``value`` (:func:`to_jsonable`; ``kwargs`` as for :func:`json.dumps`)."""
    return json.dumps(to_jsonable(value), allow_nan=False, **kwargs)


def loads_strict(text: str | bytes) -> Any:
    """Parse ``text`` as strict JSON: ``NaN``, ``Infinity`` and ``-Infinity`` are errors.

    Raises:
        ValueError: the text is not strict JSON.
    """

    def reject(constant: str) -> Any:
        raise ValueError(f"not strict JSON: {constant}")

    return json.loads(text, parse_constant=reject)
