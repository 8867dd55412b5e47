"""The warm-up steps: small runs that call every kernel a query uses, one per method and
structure mode, the degeneracy analysis and the single-call solvers."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from planarloc.localize.localizer import LocalizerConfig

#: ``update(stage, done, total)``: the progress callback of the compile and the steps.
Update = Callable[[str, int, int], None]
STEPS_STAGE = "run steps"


def step_name(method: str, structure: str) -> str:
    """The warm-up step of one estimator configuration, e.g. ``"auto tracks"``."""
    return f"{method} {structure}"


def _solver_calls() -> Callable[[], object]:
    """One call of each single-call solver API on a small fixed problem."""
    import planarloc.solvers as S
    from planarloc.geometry.pose import Pose

    xq = np.array(
        [
            [0.1, 0.2, 1.0],
            [-0.3, 0.1, 1.0],
            [0.2, -0.1, 1.0],
            [0.05, 0.3, 1.0],
            [-0.2, -0.2, 1.0],
            [0.3, 0.25, 1.0],
            [-0.1, 0.05, 1.0],
            [0.15, -0.3, 1.0],
        ]
    )
    xr = xq + np.array([0.02, 0.0, 0.0])
    rel = Pose.from_center(np.eye(3), np.array([1.0, 0.0, 0.0]))  # unit baseline to a reference
    ref1, ref2 = Pose.identity(), Pose.from_center(np.eye(3), np.array([0.0, 0.0, 2.0]))
    return lambda: (
        S.relpose_planar_2p(xq[:2], xr[:2]),
        S.relpose_5p_nister(xq[:5], xr[:5]),
        S.relpose_5p_stewenius(xq[:5], xr[:5]),
        S.relpose_8p(xq, xr),
        S.essentials_5p_nister(xq[:5], xr[:5]),
        S.essentials_5p_stewenius(xq[:5], xr[:5]),
        S.essential_8p(xq, xr),
        S.abspose_up2p(xq[:2], 5 * xq[:2]),
        S.abspose_2p2p(rel, rel, ref1, ref2),
        S.abspose_2p1p(rel, ref1, ref2, xq[0], xr[0]),
    )


def warmup_steps() -> list[tuple[str, Callable[[], object]]]:
    """``(name, run)`` of every warm-up step: each method with ``structure="none"`` and
    ``"tracks"`` on a spread scene, 2p1p on a collinear scene (the degeneracy analysis: map
    covariance and cost profile), and the single-call solver APIs."""
    from planarloc.robust.absolute_pose import estimate_absolute_pose
    from planarloc.robust.options import Method, RansacOptions
    from planarloc.synthetic.scenes import make_scene

    rng = np.random.default_rng(0)
    spread = make_scene(rng, num_refs=3, matches_per_pair=30, noise_px=1.0, outlier_ratio=0.3, track_pool=1.5)
    line = make_scene(rng, num_refs=3, matches_per_pair=30, noise_px=1.0, outlier_ratio=0.2, collinear=True)
    opts = RansacOptions(max_iterations=20, min_iterations=20)

    def on_spread(method: Method, structure: str) -> Callable[[], object]:
        return lambda: estimate_absolute_pose(
            spread.query_camera,
            spread.pairs,
            method,
            RansacOptions(max_iterations=20, min_iterations=20, structure=structure),
        )

    steps: list[tuple[str, Callable[[], object]]] = [
        (step_name(m.value, s), on_spread(m, s)) for m in Method for s in ("none", "tracks")
    ]
    steps.append(
        ("2p1p collinear", lambda: estimate_absolute_pose(line.query_camera, line.pairs, "2p1p", opts))
    )
    steps.append(("solvers", _solver_calls()))
    return steps


def run_steps(names: Iterable[str] | None = None, update: Update | None = None) -> dict[str, float]:
    """Run warm-up steps (all by default) in this process; returns seconds per step."""
    steps = warmup_steps()
    if names is not None:
        wanted = set(names)
        steps = [s for s in steps if s[0] in wanted]
    times = {}
    if update is not None:
        update(STEPS_STAGE, 0, len(steps))
    for i, (name, fn) in enumerate(steps):
        t0 = time.perf_counter()
        fn()
        times[name] = time.perf_counter() - t0
        if update is not None:
            update(STEPS_STAGE, i + 1, len(steps))
    return times


def steps_for(configs: Iterable[LocalizerConfig]) -> list[str]:
    """The warm-up steps that localizing with these configurations needs (one per method and
    structure mode)."""
    from planarloc.robust.options import parse_method, parse_structure

    # The configurations hold the members (their __post_init__ parses); the fields' types also admit a name.
    return sorted(
        {step_name(parse_method(c.method).value, parse_structure(c.ransac.structure).value) for c in configs}
    )
