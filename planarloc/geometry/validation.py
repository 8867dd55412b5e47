"""One place that checks user input at public boundaries.

Every public function of planarloc validates its array arguments with :func:`check_array`
so that bad input fails early with a message that names the argument, the expected shape
and what was actually passed, instead of failing deep inside numpy or, worse, returning a
wrong answer. Scalar options (the fields of the options dataclasses) go through
:func:`check_integer` and :func:`check_positive`, whose messages name the option the same way
(``TrackerOptions.corners: expected an integer >= 3, got 2``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit

_FLOAT64 = np.dtype(np.float64)


class InputError(ValueError):
    """Raised for invalid user input (wrong shape, non-finite values, bad parameters).

    Subclasses :class:`ValueError`, so ``except ValueError`` catches it.
    """


def check_integer(name: str, value: object, minimum: int, *, allow_none: bool = False) -> None:
    """Raise :class:`InputError` naming ``name`` unless ``value`` is an integer ``>= minimum``.

    Python and NumPy integers count, ``bool`` does not (``True`` is no count). With
    ``allow_none``, None passes too (an optional setting).
    """
    if allow_none and value is None:
        return
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        expected = f"None or an integer >= {minimum}" if allow_none else f"an integer >= {minimum}"
        raise InputError(f"{name}: expected {expected}, got {value!r}")


def check_positive(name: str, value: object, *, allow_none: bool = False) -> None:
    """Raise :class:`InputError` naming ``name`` unless ``value`` is a finite number ``> 0``.

    Python and NumPy integers and floats count, ``bool`` does not. With ``allow_none``, None
    passes too.
    """
    if allow_none and value is None:
        return
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float, np.integer, np.floating))
        or not (np.isfinite(value) and value > 0)
    ):
        expected = "None or a finite number > 0" if allow_none else "a finite number > 0"
        raise InputError(f"{name}: expected {expected}, got {value!r}")


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
        The input as a contiguous array of ``dtype``; a writable copy if it was read-only (so
        that the compiled kernels always see the same array type and never recompile).

    Raises:
        InputError: with expected vs. actual shape, or the index of the first non-finite entry.
    """
    try:
        arr: np.ndarray = np.ascontiguousarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a numeric array, got {type(value).__name__} ({exc})") from None
    if not arr.flags.writeable:
        arr = arr.copy()
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


def plain_float64_pair(a: object, b: object, ndim: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``(a, b)`` if both are exactly writable C-contiguous float64 ``ndarray``s with ``ndim``
    dimensions, else None.

    The gate of the single-call solver APIs (which all take two arrays): such input goes
    straight to a compiled kernel that validates the values itself (:func:`rays_invalid`);
    anything else (lists, other dtypes, views with strides, read-only arrays, subclasses) goes
    through :func:`check_array`, which converts it or raises its usual message. Costs ~0.35 µs.
    The pair comes back typed as arrays, so a caller passes it on without a cast::

        pair = plain_float64_pair(x_query, x_ref, 2)
        n = kernel(*pair, out) if pair is not None else -1
    """
    if type(a) is not np.ndarray or type(b) is not np.ndarray:
        return None
    if a.dtype is not _FLOAT64 or b.dtype is not _FLOAT64 or a.ndim != ndim or b.ndim != ndim:
        return None
    fa, fb = a.flags, b.flags
    return (a, b) if fa.c_contiguous and fb.c_contiguous and fa.writeable and fb.writeable else None


def are_plain_float64(a: object, b: object, ndim: int) -> bool:
    """True if :func:`plain_float64_pair` accepts ``a`` and ``b``: both exactly writable
    C-contiguous float64 ``ndarray``s with ``ndim`` dimensions."""
    return plain_float64_pair(a, b, ndim) is not None


@njit(cache=True)
def rays_invalid(xq: np.ndarray, xr: np.ndarray, rows: int, min_rows: int, nonzero: bool) -> bool:
    """Kernel twin of the correspondence checks: True if the two (N, 3) ray arrays are invalid.

    Invalid: a second dimension other than 3, ``N != rows`` (if ``rows >= 0``), ``N <
    min_rows``, different ``N``, a NaN/inf entry, or (if ``nonzero``) an all-zero row. These
    are exactly the conditions under which
    :func:`planarloc.geometry.essential_decomposition.check_correspondences` raises, so a
    caller that gets True calls it for the message.
    """
    n = xq.shape[0]
    if xq.shape[1] != 3 or xr.shape[1] != 3 or xr.shape[0] != n or n < min_rows or (rows >= 0 and n != rows):
        return True
    return _rows_invalid(xq, nonzero) or _rows_invalid(xr, nonzero)


@njit(cache=True)
def _rows_invalid(x: np.ndarray, nonzero: bool) -> bool:
    """True if a row of the (N, 3) array x has a NaN/inf entry or (if ``nonzero``) is all zero."""
    for i in range(x.shape[0]):
        a, b, c = x[i, 0], x[i, 1], x[i, 2]
        if not (np.isfinite(a) and np.isfinite(b) and np.isfinite(c)):
            return True
        if nonzero and a == 0.0 and b == 0.0 and c == 0.0:
            return True
    return False


def check_rotation(name: str, R: object, tol: float = 1e-6) -> np.ndarray:
    """Check that ``R`` is a 3x3 rotation matrix (orthonormal, det = +1) within ``tol``."""
    R = check_array(name, R, (3, 3))
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > tol or np.linalg.det(R) < 0:
        raise InputError(
            f"{name}: not a rotation matrix (|R Rᵀ - I|max = {err:.2e}, det = {np.linalg.det(R):+.3f}); "
            "hint: poses must be proper rigid transforms; re-orthonormalise with "
            "scipy.spatial.transform.Rotation"
        )
    return R
