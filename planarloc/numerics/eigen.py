"""Real eigenvalues of a small dense nonsymmetric matrix (numba port of EISPACK ``hqr``).

Route: balancing (``balanc``), reduction to upper Hessenberg form by stabilised elementary
similarity transformations (``elmhes``), then the shifted double-step QR algorithm (``hqr``).
Arrays are 1-based ``(n + 1, n + 1)`` internally, as in the original.

References:
    J. H. Wilkinson, C. Reinsch, *Handbook for Automatic Computation*, vol. II, 1971 (EISPACK
    ``balanc``, ``elmhes``, ``hqr``); Press et al., *Numerical Recipes*, 3rd ed., Sec. 11.6-11.7.
    Used instead of numba's ``np.linalg.eig``, which needs complex input and a LAPACK call
    costing ~150 µs per 10 × 10 matrix.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["real_eigenvalues"]

REAL_TOL = 1e-10  # |imaginary part| <= REAL_TOL max(1, |λ|): the eigenvalue counts as real


@njit(cache=True)
def _balance(a, n):
    """Similarity scaling by powers of 2 so that row and column norms are comparable."""
    radix = 2.0
    sqrdx = radix * radix
    done = False
    while not done:
        done = True
        for i in range(1, n + 1):
            r = 0.0
            c = 0.0
            for j in range(1, n + 1):
                if j != i:
                    c += abs(a[j, i])
                    r += abs(a[i, j])
            if c != 0.0 and r != 0.0:
                g = r / radix
                f = 1.0
                s = c + r
                while c < g:
                    f *= radix
                    c *= sqrdx
                g = r * radix
                while c > g:
                    f /= radix
                    c /= sqrdx
                if (c + r) / f < 0.95 * s:
                    done = False
                    g = 1.0 / f
                    for j in range(1, n + 1):
                        a[i, j] *= g
                    for j in range(1, n + 1):
                        a[j, i] *= f


@njit(cache=True)
def _hessenberg(a, n):
    """Reduction to upper Hessenberg form by Gaussian elimination with pivoting."""
    for m in range(2, n):
        x = 0.0
        i = m
        for j in range(m, n + 1):
            if abs(a[j, m - 1]) > abs(x):
                x = a[j, m - 1]
                i = j
        if i != m:
            for j in range(m - 1, n + 1):
                a[i, j], a[m, j] = a[m, j], a[i, j]
            for j in range(1, n + 1):
                a[j, i], a[j, m] = a[j, m], a[j, i]
        if x != 0.0:
            for i in range(m + 1, n + 1):
                y = a[i, m - 1]
                if y != 0.0:
                    y /= x
                    a[i, m - 1] = 0.0  # (EISPACK keeps the multiplier here; we do not need it)
                    for j in range(m, n + 1):
                        a[i, j] -= y * a[m, j]
                    for j in range(1, n + 1):
                        a[j, m] += y * a[j, i]


@njit(cache=True)
def _small_subdiagonal(a, nn, anorm) -> int:
    """Lowest l ≤ nn such that a[l, l−1] is negligible (set to 0) or l = 1: the active block is l..nn."""
    l = nn
    while l >= 2:
        s = abs(a[l - 1, l - 1]) + abs(a[l, l])
        if s == 0.0:
            s = anorm
        if abs(a[l, l - 1]) + s == s:
            a[l, l - 1] = 0.0
            break
        l -= 1
    return l


@njit(cache=True)
def _two_roots(x, y, w, t, nn, wr, wi) -> None:
    """Eigenvalues nn−1, nn of the deflated 2×2 block [[y, ·], [·, x]] with off-diagonal
    product w (shift t)."""
    p = 0.5 * (y - x)
    q = p * p + w
    z = np.sqrt(abs(q))
    x += t
    if q >= 0.0:
        z = p + (z if p >= 0.0 else -z)
        wr[nn - 1] = wr[nn] = x + z
        if z != 0.0:
            wr[nn] = x - w / z
        wi[nn - 1] = wi[nn] = 0.0
    else:
        wr[nn - 1] = wr[nn] = x + p
        wi[nn - 1] = -z
        wi[nn] = z


@njit(cache=True)
def _francis_start(a, nn, l, x, y, w):
    """Start row m of the double-shift sweep (two small consecutive subdiagonals) and the first
    column (p, q, r) of the shifted matrix, normalised; returns ``(m, p, q, r)``."""
    m = nn - 2
    p = q = r = 0.0
    while m >= l:
        z = a[m, m]
        r = x - z
        s = y - z
        p = (r * s - w) / a[m + 1, m] + a[m, m + 1]
        q = a[m + 1, m + 1] - z - r - s
        r = a[m + 2, m + 1]
        s = abs(p) + abs(q) + abs(r)
        p /= s
        q /= s
        r /= s
        if m == l:
            break
        u = abs(a[m, m - 1]) * (abs(q) + abs(r))
        v = abs(p) * (abs(a[m - 1, m - 1]) + abs(z) + abs(a[m + 1, m + 1]))
        if u + v == v:
            break
        m -= 1
    return m, p, q, r


@njit(cache=True)
def _francis_sweep(a, nn, l, m, p, q, r) -> None:
    """One double-shift QR step on rows/columns m..nn by Householder reflections, chasing the bulge."""
    for i in range(m + 2, nn + 1):
        a[i, i - 2] = 0.0
        if i != m + 2:
            a[i, i - 3] = 0.0
    x = 0.0
    for k in range(m, nn):
        if k != m:
            p = a[k, k - 1]
            q = a[k + 1, k - 1]
            r = 0.0
            if k != nn - 1:
                r = a[k + 2, k - 1]
            x = abs(p) + abs(q) + abs(r)
            if x != 0.0:
                p /= x
                q /= x
                r /= x
        s = np.sqrt(p * p + q * q + r * r)
        if p < 0.0:
            s = -s
        if s == 0.0:
            continue
        if k == m:
            if l != m:
                a[k, k - 1] = -a[k, k - 1]
        else:
            a[k, k - 1] = -s * x
        p += s
        x = p / s
        y = q / s
        z = r / s
        q /= p
        r /= p
        for j in range(k, nn + 1):
            p = a[k, j] + q * a[k + 1, j]
            if k != nn - 1:
                p += r * a[k + 2, j]
                a[k + 2, j] -= p * z
            a[k + 1, j] -= p * y
            a[k, j] -= p * x
        mmin = nn if nn < k + 3 else k + 3
        for i in range(l, mmin + 1):
            p = x * a[i, k] + y * a[i, k + 1]
            if k != nn - 1:
                p += z * a[i, k + 2]
                a[i, k + 2] -= p * r
            a[i, k + 1] -= p * q
            a[i, k] -= p


@njit(cache=True)
def _hqr(a, n, wr, wi) -> bool:
    """All eigenvalues of an upper Hessenberg matrix by the shifted double-step QR algorithm.

    EISPACK ``hqr`` (Wilkinson & Reinsch, Handbook vol. II); a is destroyed. Returns False if
    an eigenvalue needs more than 30 iterations.
    """
    anorm = 0.0
    for i in range(1, n + 1):
        for j in range(max(i - 1, 1), n + 1):
            anorm += abs(a[i, j])
    nn = n
    t = 0.0
    while nn >= 1:
        its = 0
        while True:
            l = _small_subdiagonal(a, nn, anorm)
            x = a[nn, nn]
            if l == nn:  # one root found
                wr[nn] = x + t
                wi[nn] = 0.0
                nn -= 1
            else:
                y = a[nn - 1, nn - 1]
                w = a[nn, nn - 1] * a[nn - 1, nn]
                if l == nn - 1:  # two roots found
                    _two_roots(x, y, w, t, nn, wr, wi)
                    nn -= 2
                else:
                    if its == 30:
                        return False
                    if its == 10 or its == 20:  # exceptional shift
                        t += x
                        for i in range(1, nn + 1):
                            a[i, i] -= x
                        s = abs(a[nn, nn - 1]) + abs(a[nn - 1, nn - 2])
                        x = y = 0.75 * s
                        w = -0.4375 * s * s
                    its += 1
                    m, p, q, r = _francis_start(a, nn, l, x, y, w)
                    _francis_sweep(a, nn, l, m, p, q, r)
            if nn < 1 or l >= nn - 1:
                break
    return True


@njit(cache=True)
def real_eigenvalues(M: np.ndarray, out: np.ndarray) -> int:
    """Real eigenvalues of a square matrix (balance, Hessenberg, hqr); returns their count."""
    n = M.shape[0]
    a = np.zeros((n + 1, n + 1))
    for i in range(n):
        for j in range(n):
            a[i + 1, j + 1] = M[i, j]
    _balance(a, n)
    _hessenberg(a, n)
    wr = np.zeros(n + 1)
    wi = np.zeros(n + 1)
    if not _hqr(a, n, wr, wi):
        return 0
    count = 0
    for i in range(1, n + 1):
        if abs(wi[i]) <= REAL_TOL * max(1.0, abs(wr[i])):
            if wi[i] != 0.0 and wi[i] < 0.0:
                continue  # a split double root: keep one of the conjugate pair
            out[count] = wr[i]
            count += 1
    return count
