"""Real roots by Sturm sequences (planarloc.numerics.sturm)."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.numerics.sturm import polyval, real_roots_sturm


def test_sturm_real_roots():
    rng = np.random.default_rng(17)
    out = np.empty(10)
    for k in range(200):
        n_real = 2 * rng.integers(0, 6)  # 0, 2, ..., 10 real roots; the rest complex pairs
        roots = rng.normal(scale=3, size=n_real)
        coeffs = np.poly1d([rng.uniform(0.1, 10) * rng.choice([-1, 1])])
        for r in roots:
            coeffs *= np.poly1d([1.0, -r])
        for _ in range((10 - n_real) // 2):
            a, b = rng.normal(), rng.uniform(0.5, 2)
            coeffs *= np.poly1d([1.0, -2 * a, a * a + b * b])
        c = coeffs.coeffs[::-1].copy()  # ascending
        count = real_roots_sturm(c, out)
        if np.min(np.diff(np.sort(roots)), initial=np.inf) > 1e-3:
            assert count == n_real
            assert np.allclose(np.sort(out[:count]), np.sort(roots), atol=1e-8)
    # a double root is reported once; a constant or zero polynomial has no roots
    assert real_roots_sturm(np.array([1.0, -2.0, 1.0]), out) == 1 and out[0] == pytest.approx(1.0, abs=1e-6)
    assert real_roots_sturm(np.array([3.0, 0.0, 0.0]), out) == 0
    assert real_roots_sturm(np.zeros(11), out) == 0


def test_polyval_is_horner_in_ascending_order():
    c = np.array([1.0, -2.0, 0.5, 3.0])
    for z in (-2.0, 0.0, 0.3, 7.0):
        assert polyval(c, 3, z) == pytest.approx(np.polyval(c[::-1], z), rel=1e-14)
    assert polyval(c, 1, 2.0) == pytest.approx(1.0 - 4.0)  # only the first deg + 1 coefficients
