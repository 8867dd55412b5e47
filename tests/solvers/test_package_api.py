"""``planarloc.solvers.<name>`` is the solver function (the submodules do not shadow it)."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

import planarloc.solvers as S

NAMES = [
    "relpose_planar_2p",
    "relpose_5p_nister",
    "relpose_5p_stewenius",
    "relpose_8p",
    "abspose_2p1p",
    "abspose_2p2p",
    "abspose_up2p",
]


@pytest.mark.parametrize("name", NAMES)
def test_package_attribute_is_the_function(name: str) -> None:
    module = importlib.import_module(f"planarloc.solvers.{name}")  # importing again must not rebind
    fn = getattr(S, name)
    assert callable(fn) and fn is getattr(module, name)
    assert name in S.__all__


def test_package_function_solves() -> None:
    from planarloc.geometry.planar import relpose_from_planar_params

    truth = relpose_from_planar_params(0.2, 0.5)
    X = np.array([[1.0, -0.5, 6.0], [-2.0, 0.8, 9.0]])
    xq = X / X[:, 2:]
    Xr = X @ truth.R.T + truth.t
    poses = S.relpose_planar_2p(xq, Xr / Xr[:, 2:])
    assert any(
        np.allclose(p.R, truth.R) and np.allclose(p.t, truth.t / np.linalg.norm(truth.t)) for p in poses
    )
