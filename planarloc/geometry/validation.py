"""One place that checks user input at public boundaries.

Every public function of planarloc validates its array arguments with :func:`check_array`
so that bad input fails early with a message that names the argument, the expected shape
and what was actually passed, instead of failing deep inside numpy or, worse, returning a
wrong answer.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


class InputError(ValueError):
    """Raised for invalid user input (wrong shape, non-finite values, bad parameters).

    Subclasses :class:`ValueError`, so ``except ValueError`` catches it.
    """


def _shape_str(shape: Sequence[int | None]) -> str:
    inner = ", ".join("N" if s is None else str(s) for s in shape)
    return f"({inner},)" if len(shape) == 1 else f"({inner})"


def check_array(
    name: str,
    value: object,
    shape: Sequence[int | None] | None = None,
    *,
    finite: bool = True,
    dtype: type = np.float64,
    min_rows: int | None = None,
) -> np.ndarray:
    """Convert ``value`` to an array and check its shape and values.

    Args:
        name: argument name used in error messages.
        value: array-like input.
        shape: expected shape; ``None`` entries accept any size. ``None`` skips the check.
        finite: reject NaN and inf.
        dtype: dtype of the returned array.
        min_rows: if given, the first dimension must be at least this large.

    Returns:
        The input as a contiguous array of ``dtype``.

    Raises:
        InputError: with expected vs. actual shape, or the index of the first non-finite entry.
    """
    try:
        arr = np.ascontiguousarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a numeric array, got {type(value).__name__} ({exc})") from None
    if shape is not None:
        ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape))
        if not ok:
            raise InputError(f"{name}: expected shape {_shape_str(shape)}, got {tuple(arr.shape)}")
    if min_rows is not None and (arr.ndim == 0 or arr.shape[0] < min_rows):
        got = 0 if arr.ndim == 0 else arr.shape[0]
        raise InputError(f"{name}: need at least {min_rows} rows, got {got}")
    if finite and arr.size and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise InputError(f"{name}: contains NaN or inf (first at index {tuple(int(i) for i in bad)})")
    return arr


def check_array_fast(name: str, value: object, shape: Sequence[int | None], min_rows: int | None = None
                     ) -> np.ndarray:
    """:func:`check_array` (finite, float64) with a fast path for valid input.

    For the single-call solver APIs, where the full check cost more than the solve: one
    conversion, a shape comparison and one reduction (a finite sum means finite entries).
    Anything unusual goes through :func:`check_array`, which raises its usual messages.
    """
    arr = value if type(value) is np.ndarray and value.dtype == np.float64 else None
    if arr is None or not arr.flags.c_contiguous or arr.ndim != len(shape) or (
            min_rows is not None and arr.shape[0] < min_rows):
        return check_array(name, value, shape, min_rows=min_rows)
    for s, a in zip(shape, arr.shape):
        if s is not None and s != a:
            return check_array(name, value, shape, min_rows=min_rows)
    if not np.isfinite(arr.sum()):
        return check_array(name, value, shape, min_rows=min_rows)
    return arr


def check_rotation(name: str, R: object, tol: float = 1e-6) -> np.ndarray:
    """Check that ``R`` is a 3x3 rotation matrix (orthonormal, det = +1) within ``tol``."""
    R = check_array(name, R, (3, 3))
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > tol or np.linalg.det(R) < 0:
        raise InputError(
            f"{name}: not a rotation matrix (|R Rᵀ - I|max = {err:.2e}, det = {np.linalg.det(R):+.3f}); "
            "hint: poses must be proper rigid transforms; re-orthonormalise with scipy.spatial.transform.Rotation"
        )
    return R
