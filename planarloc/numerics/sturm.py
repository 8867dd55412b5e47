"""All distinct real roots of a univariate polynomial by Sturm sequences (numba kernels).

Coefficients are in ascending order: ``c[0] + c[1] z + ... + c[n] z^n``.

References:
    Sturm's theorem, as used for the five-point problem by D. Nistér, "An efficient solution to
    the five-point relative pose problem", IEEE TPAMI 26(6), 2004, Sec. 3, step "extraction of
    roots" (bisection on Sturm sequences, then polishing). Polishing: Newton steps safeguarded by
    bisection (``rtsafe``, Press et al., *Numerical Recipes*, 3rd ed., Sec. 9.4).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["polyval", "real_roots_sturm"]


@njit(cache=True)
def polyval(c: np.ndarray, deg: int | np.integer, z: float) -> float:
    """Horner evaluation of ``c[0] + ... + c[deg] z^deg``."""
    r = c[deg]
    for k in range(deg - 1, -1, -1):
        r = r * z + c[k]
    return r


@njit(cache=True)
def _sign_changes(S, degs, ns, quot, linear, z) -> int:
    """Sign changes of the Sturm sequence at z.

    In the generic case every remainder lowers the degree by one and the sequence obeys
    ``S[k+1] = c_k ((a_k z + b_k) S[k] − S[k−1])`` (``quot[k] = (a_k, b_k, c_k)``), so for
    ``|z| ≤ 1`` only S[0] and S[1] are evaluated by Horner's rule. For larger ``|z|`` the
    recurrence cancels ~``z²`` per step, so each member is evaluated directly.
    """
    count = 0
    prev = polyval(S[0], degs[0], z)
    cur = polyval(S[1], degs[1], z)
    last = prev
    for k in range(1, ns):
        if k >= 2:
            if linear and abs(z) <= 1.0:
                nxt = quot[k - 1, 2] * ((quot[k - 1, 0] * z + quot[k - 1, 1]) * cur - prev)
            else:
                nxt = polyval(S[k], degs[k], z)
            prev = cur
            cur = nxt
        if cur != 0.0:
            if last != 0.0 and (cur > 0.0) != (last > 0.0):
                count += 1
            last = cur
        elif last == 0.0:
            last = cur
    return count


@njit(cache=True)
def _sign_changes_at_infinity(S: np.ndarray, degs: np.ndarray, ns: int, positive: bool | np.bool_) -> int:
    count = 0
    last = 0.0
    for k in range(ns):
        v = S[k, degs[k]]
        if not positive and degs[k] % 2 == 1:
            v = -v
        if v != 0.0:
            if last != 0.0 and (v > 0.0) != (last > 0.0):
                count += 1
            last = v
    return count


@njit(cache=True)
def _newton_bisect(c: np.ndarray, deg: int, lo: float, hi: float) -> float:
    """Root of ``c`` in the bracket [lo, hi] by Newton steps safeguarded by bisection.

    NaN if ``c`` has the same sign at both ends (no bracket).
    """
    flo = polyval(c, deg, lo)
    fhi = polyval(c, deg, hi)
    if flo == 0.0:
        return lo
    if fhi == 0.0:
        return hi
    if (flo > 0.0) == (fhi > 0.0):
        return np.nan  # no sign change: even multiplicity
    # orient so that f(xl) < 0 < f(xh)
    if flo < 0.0:
        xl, xh = lo, hi
    else:
        xl, xh = hi, lo
    x = 0.5 * (lo + hi)
    dxold = abs(hi - lo)
    dx = dxold
    for _ in range(100):
        f = c[deg]
        df = 0.0
        bound = abs(c[deg])  # sum |c_k| |x|^k: the rounding error of f is below ~2 deg eps bound
        ax = abs(x)
        for k in range(deg - 1, -1, -1):
            df = df * x + f
            f = f * x + c[k]
            bound = bound * ax + abs(c[k])
        if abs(f) <= 4.0 * deg * 2.2e-16 * bound:
            return x  # f is rounding noise: x is a root to working precision
        if f < 0.0:
            xl = x
        else:
            xh = x
        if ((x - xh) * df - f) * ((x - xl) * df - f) > 0.0 or abs(2.0 * f) > abs(dxold * df):
            dxold = dx
            dx = 0.5 * (xh - xl)
            x = xl + dx
        else:
            dxold = dx
            dx = f / df
            x -= dx
        if abs(dx) <= 4e-16 * max(abs(x), 1e-300):
            return x
    return x


@njit(cache=True, inline="always")
def _effective_degree(coeffs: np.ndarray) -> int:
    """Degree once leading coefficients below 1e-15 of the largest are dropped (0 for p ≡ 0)."""
    n = coeffs.shape[0] - 1
    scale = 0.0
    for k in range(n + 1):
        scale = max(scale, abs(coeffs[k]))
    if scale == 0.0:
        return 0
    while n > 0 and abs(coeffs[n]) <= 1e-15 * scale:
        n -= 1
    return n


@njit(cache=True, inline="always")
def _sturm_sequence(coeffs: np.ndarray, n: int, S: np.ndarray, degs: np.ndarray, quot: np.ndarray):
    """Fill the Sturm sequence ``p/lead, p'/n, −rem, ...`` of the degree-``n`` polynomial.

    ``S`` (n + 2, n + 1): rows are the members (the last row is scratch for remainders),
    ``degs`` their degrees, ``quot`` row k: (a, b, c) with S[k+1] = c ((a z + b) S[k] − S[k−1]).
    Returns ``(ns, multiple, linear)``: the number of members, whether p has multiple roots
    (the sequence ends at gcd(p, p')), and whether every quotient is linear (the fast
    recurrence of :func:`_sign_changes` applies).
    """
    multiple = False
    linear = True
    lead = coeffs[n]
    for k in range(n + 1):
        S[0, k] = coeffs[k] / lead
    degs[0] = n
    for k in range(1, n + 1):
        S[1, k - 1] = k * S[0, k] / n
    degs[1] = n - 1
    ns = 2
    r = S[n + 1]
    while degs[ns - 1] > 0:
        # remainder of S[ns-2] divided by S[ns-1]
        da = degs[ns - 2]
        db = degs[ns - 1]
        big = 0.0
        for k in range(da + 1):
            r[k] = S[ns - 2, k]
            big = max(big, abs(r[k]))
        b = S[ns - 1]
        q0 = q1 = 0.0
        for k in range(da - db, -1, -1):
            f = r[k + db] / b[db]
            for j in range(db + 1):
                r[k + j] -= f * b[j]
            r[k + db] = 0.0
            if k == 1:
                q1 = f
            elif k == 0:
                q0 = f
        dr = db - 1
        while dr >= 0 and abs(r[dr]) <= 1e-14 * big:
            dr -= 1
        if dr < 0:
            multiple = True
            break
        if da - db != 1 or dr != db - 1:
            linear = False
        # S_next = −r / |leading coefficient| (a positive scale keeps the signs)
        c = 1.0 / abs(r[dr])
        for k in range(dr + 1):
            S[ns, k] = -r[k] * c
        quot[ns - 1, 0], quot[ns - 1, 1], quot[ns - 1, 2] = q1, q0, c
        degs[ns] = dr
        ns += 1
    return ns, multiple, linear


@njit(cache=True, inline="always")
def _root_bound(S: np.ndarray, degs: np.ndarray, ns: int, quot: np.ndarray, linear: bool, n: int):
    """``(bound, v_lo, v_hi)``: every real root lies in (−bound, bound) (Fujiwara's bound on the
    monic S[0]), with the sign-change counts at both ends."""
    bound = 0.0
    for k in range(1, n + 1):
        a = abs(S[0, n - k])
        if k == n:
            a *= 0.5
        if a > 0.0:
            bound = max(bound, a ** (1.0 / k))
    bound = 2.0 * bound * (1.0 + 1e-12) + 1e-300
    v_lo = _sign_changes(S, degs, ns, quot, linear, -bound)
    v_hi = _sign_changes(S, degs, ns, quot, linear, bound)
    # fall back to the counts at infinity if rounding put a root on the bound
    v_inf_lo = _sign_changes_at_infinity(S, degs, ns, np.bool_(False))  # typed, not literals: one signature
    v_inf_hi = _sign_changes_at_infinity(S, degs, ns, np.bool_(True))
    if v_lo != v_inf_lo or v_hi != v_inf_hi:
        bound *= 2.0
        v_lo = _sign_changes(S, degs, ns, quot, linear, -bound)
        v_hi = _sign_changes(S, degs, ns, quot, linear, bound)
    return bound, v_lo, v_hi


@njit(cache=True)
def real_roots_sturm(coeffs: np.ndarray, roots: np.ndarray) -> int:
    """All distinct real roots of a polynomial by Sturm sequences (Nistér 2004, Sec. 3).

    The Sturm sequence ``p, p', −rem(p, p'), ...`` counts the distinct real roots in any
    interval (Sturm's theorem). Starting from Fujiwara's bound on the root magnitudes, intervals
    are bisected until each holds exactly one root, which is then polished by Newton steps
    safeguarded by bisection to full double precision (a root of even multiplicity, where p
    does not change sign, is found as a root of the last member of the sequence,
    ``gcd(p, p')``). A cluster of roots closer than ~1e-14 relative is reported once.

    Args:
        coeffs: (n + 1,) ascending coefficients. Leading coefficients below 1e-15 of the
            largest one are treated as zero (the roots they would add are at ~1e15).
        roots: (≥ n,) output buffer.

    Returns:
        Number of real roots written to ``roots`` (0 for a polynomial that is identically 0).
    """
    n = _effective_degree(coeffs)
    if n == 0:
        return 0
    S = np.zeros((n + 2, n + 1))
    degs = np.zeros(n + 1, dtype=np.int64)
    quot = np.zeros((n + 1, 3))
    ns, multiple, linear = _sturm_sequence(coeffs, n, S, degs, quot)
    bound, v_lo, v_hi = _root_bound(S, degs, ns, quot, linear, n)
    # isolate by bisection (depth-first, explicit stack), then polish each isolated root
    stack = np.empty((2, 128))  # interval ends
    counts = np.empty((2, 128), dtype=np.int64)  # sign changes at the ends
    stack_lo, stack_hi = stack[0], stack[1]
    stack_vlo, stack_vhi = counts[0], counts[1]
    stack_lo[0], stack_hi[0], stack_vlo[0], stack_vhi[0] = -bound, bound, v_lo, v_hi
    top = 1
    count = 0
    cap = roots.shape[0]
    while top > 0:
        top -= 1
        lo, hi, vl, vh = stack_lo[top], stack_hi[top], stack_vlo[top], stack_vhi[top]
        k = vl - vh
        if k <= 0:
            continue
        if k == 1 or hi - lo <= 1e-14 * max(abs(lo), abs(hi), 1e-300) or top >= 126:
            if count < cap:
                if k == 1:
                    z = _newton_bisect(S[0], n, lo, hi)
                    if np.isnan(z) and multiple:
                        # a root of even multiplicity is a root of odd multiplicity of the gcd
                        z = _newton_bisect(S[ns - 1], degs[ns - 1], lo, hi)
                    roots[count] = 0.5 * (lo + hi) if np.isnan(z) else z
                else:
                    roots[count] = 0.5 * (lo + hi)  # root cluster, reported once
                count += 1
            continue
        mid = 0.5 * (lo + hi)
        vm = _sign_changes(S, degs, ns, quot, linear, mid)
        stack_lo[top], stack_hi[top], stack_vlo[top], stack_vhi[top] = lo, mid, vl, vm
        top += 1
        stack_lo[top], stack_hi[top], stack_vlo[top], stack_vhi[top] = mid, hi, vm, vh
        top += 1
    return count
