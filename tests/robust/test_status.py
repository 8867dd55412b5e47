"""One status enum: its string values are those results have always carried, every estimate's
status is one of its members, and no module of ``planarloc.robust`` spells a status as a string."""

from __future__ import annotations

import ast
import dataclasses
import json
from pathlib import Path

import planarloc.robust
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.options import RansacOptions
from planarloc.robust.relative_pose import RelativePoseEstimate
from planarloc.robust.result import PoseEstimate
from planarloc.robust.status import DATA_LIMITED, Status

# The strings in result files, the CLI report and the tests: they must not change (new ones are
# added to the record schema as well).
VALUES = {
    "SUCCESS": "success",
    "TOO_FEW_MATCHES": "too_few_matches",
    "NO_CONSISTENT_HYPOTHESIS": "no_consistent_hypothesis",
    "TOO_FEW_INLIERS": "too_few_inliers",
    "DEGENERATE_SCALE": "degenerate_scale",
    "DEGENERATE_STRUCTURE": "degenerate_structure",
    "SINGLE_REFERENCE": "single_reference",
    "INCONSISTENT_REFERENCES": "inconsistent_references",
    "AMBIGUOUS_POSE": "ambiguous_pose",
    "SEARCH_INCOMPLETE": "search_incomplete",
    "PLANAR_MODEL_VIOLATED": "planar_model_violated",
    "NOT_IN_MAP": "not_in_map",
}


def test_the_string_values_are_unchanged() -> None:
    """The values are those results carry, and each is one the published record schema allows."""
    assert {s.name: s.value for s in Status} == VALUES
    schema = json.loads((Path(__file__).resolve().parents[2] / "docs/schema/record.schema.json").read_text())
    assert set(VALUES.values()) | {"error"} == set(schema["$defs"]["fix"]["properties"]["status"]["enum"])
    for s in Status:
        assert s == s.value and str(s) == s.value and f"{s}" == s.value and hash(s) == hash(s.value)
        assert json.loads(json.dumps({s: s})) == {s.value: s.value}
    assert DATA_LIMITED <= set(Status) and Status.SUCCESS not in DATA_LIMITED


def test_a_string_status_becomes_its_member_and_another_string_stays_as_given() -> None:
    est = PoseEstimate(None, False, "too_few_inliers", "", [])
    assert est.status is Status.TOO_FEW_INLIERS and est.to_dict()["status"] == "too_few_inliers"
    assert RelativePoseEstimate(None, False, "too_few_matches").status is Status.TOO_FEW_MATCHES
    other = PoseEstimate(None, False, "recorded", "", [])  # a test double's own status
    assert type(other.status) is str and other.status == "recorded"


def test_estimates_carry_members(scene) -> None:
    seen = []
    sc = scene(0, num_refs=3, matches_per_pair=60, noise_px=0.5)
    est = estimate_absolute_pose(sc.query_camera, sc.pairs, "2p2p", RansacOptions(seed=0))
    seen.append(est.status)
    assert est.success and est.status is Status.SUCCESS
    one_each = [
        dataclasses.replace(
            p, query_points=p.query_points[:1], ref_points=p.ref_points[:1], query_indices=p.query_indices[:1]
        )
        for p in sc.pairs
    ]
    few = estimate_absolute_pose(sc.query_camera, one_each, "2p2p", RansacOptions(structure="none", seed=0))
    seen.append(few.status)
    assert few.status is Status.TOO_FEW_MATCHES
    line = scene(0, noise_px=0.0, num_refs=5, matches_per_pair=100, collinear=True, track_pool=2)
    flat = estimate_absolute_pose(
        line.query_camera,
        line.pairs,
        "2p1p",
        RansacOptions(max_iterations=100, min_iterations=100, structure="none", seed=0),
    )
    seen.append(flat.status)
    assert flat.status is Status.DEGENERATE_SCALE
    assert all(type(s) is Status for s in seen)
    assert [json.loads(json.dumps(e.to_dict()))["status"] for e in (est, few, flat)] == [
        "success",
        "too_few_matches",
        "degenerate_scale",
    ]


def _status_literals(path: Path) -> list[tuple[int, str]]:
    """String constants equal to a status value, but docstrings and dict keys."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    skip = set()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (
            isinstance(body, list)
            and body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
        ):
            skip.add(id(body[0].value))
        if isinstance(node, ast.Dict):
            skip.update(id(k) for k in node.keys if k is not None)
    values = set(VALUES.values())
    return [
        (n.lineno, n.value)
        for n in ast.walk(tree)
        if isinstance(n, ast.Constant) and n.value in values and id(n) not in skip
    ]


def test_no_module_of_robust_spells_a_status_as_a_string() -> None:
    root = Path(planarloc.robust.__file__).parent
    found = {
        p.name: hits
        for p in sorted(root.glob("*.py"))
        if p.name != "status.py"
        for hits in [_status_literals(p)]
        if hits
    }
    assert found == {}
    assert _status_literals(root / "status.py")  # the check sees the values where they are defined
