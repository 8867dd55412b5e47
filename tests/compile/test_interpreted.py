"""Kernels run as Python while they compile (planarloc.compile.interpreted): the same estimates as the
compiled kernels, nothing compiled for a kernel that runs as Python, the hot kernels still compiled, and
every dispatcher restored afterwards."""

from __future__ import annotations

import numpy as np
import pytest
from numba.core.registry import CPUDispatcher

from planarloc.compile.dispatchers import dispatcher, planarloc_dispatchers
from planarloc.compile.interpreted import HOT_KERNELS, interpreted_kernels, running_as_python
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.options import RansacOptions
from planarloc.synthetic.scenes import make_scene

SO3_EXP = "planarloc.geometry.so3:exp_so3"


def test_the_hot_kernels_exist_and_stay_compiled_while_the_others_run_as_python() -> None:
    assert all(isinstance(dispatcher(k), CPUDispatcher) for k in HOT_KERNELS)  # a rename would break this
    everything = planarloc_dispatchers()
    with interpreted_kernels() as kernels:
        as_python = set(running_as_python())
        assert kernels.active and as_python == set(everything) - set(HOT_KERNELS)
        assert all(type(everything[k]) is CPUDispatcher for k in HOT_KERNELS)
    assert running_as_python() == [] and all(type(d) is CPUDispatcher for d in everything.values())


def test_a_kernel_run_as_python_compiles_nothing_and_gives_the_compiled_answer() -> None:
    exp = dispatcher(SO3_EXP)
    assert exp is not None
    w = np.array([0.1, -0.2, 0.3], dtype=np.float32)  # float32: a signature no caller compiles
    before = list(exp.signatures)
    with interpreted_kernels():
        as_python = exp(w)
        assert exp.signatures == before  # ran as Python: numba compiled nothing
    np.testing.assert_allclose(as_python, exp(w.astype(np.float64)), atol=1e-6)  # the compiled kernel


def test_end_returns_to_compiled_kernels_inside_the_block_and_blocks_nest() -> None:
    with interpreted_kernels() as outer:
        with interpreted_kernels() as inner:
            assert not inner.active  # the outer block swapped them: the inner one leaves them alone
        assert SO3_EXP in running_as_python()
        outer.end()
        assert running_as_python() == [] and not outer.active
        outer.end()  # idempotent
    assert running_as_python() == []


@pytest.mark.parametrize("method", ["auto", "2p1p", "2p2p"])
def test_estimates_as_python_equal_the_compiled_ones(method: str) -> None:
    rng = np.random.default_rng(41)
    scenes = [
        make_scene(rng, num_refs=3, matches_per_pair=40, noise_px=1.0, outlier_ratio=outliers)
        for outliers in (0.0, 0.3, 0.5)
    ]
    options = RansacOptions(seed=7)
    compiled = [estimate_absolute_pose(sc.query_camera, sc.pairs, method, options) for sc in scenes]
    with interpreted_kernels():
        as_python = [estimate_absolute_pose(sc.query_camera, sc.pairs, method, options) for sc in scenes]
    assert sum(e.success for e in compiled) >= 2  # the comparison covers poses, not only failures
    for a, b in zip(compiled, as_python, strict=True):
        assert (a.status, a.num_inliers, a.model) == (b.status, b.num_inliers, b.model)
        if a.success:
            np.testing.assert_allclose(b.pose.R, a.pose.R, atol=1e-9)
            np.testing.assert_allclose(b.pose.t, a.pose.t, atol=1e-9)
            assert b.position_std_m == pytest.approx(a.position_std_m, rel=1e-6)
