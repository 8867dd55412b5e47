"""Conventions of :class:`planarloc.geometry.pose.Pose` (docs/conventions.md, "Poses").

Property-based (hypothesis) round trips: composition/inverse, associativity, quaternion order
and sign, camera centre, transform, matrix constructors; and the validation errors.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from planarloc.geometry.pose import Pose, pose_errors, rotation_error_deg
from planarloc.geometry.validation import InputError

TOL = 1e-9

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
coord = st.floats(-100.0, 100.0, allow_nan=False, allow_infinity=False)


@st.composite
def quats(draw) -> np.ndarray:
    """Unit quaternions (w, x, y, z), any sign, away from the zero vector."""
    q = np.array([draw(finite) for _ in range(4)])
    if np.linalg.norm(q) < 1e-3:
        q = np.array([1.0, 0.0, 0.0, 0.0])
    return q / np.linalg.norm(q)


@st.composite
def vec3(draw) -> np.ndarray:
    return np.array([draw(coord) for _ in range(3)])


@st.composite
def poses(draw) -> Pose:
    return Pose.from_quat_wxyz(draw(quats()), draw(vec3()))


@st.composite
def points(draw) -> np.ndarray:
    n = draw(st.integers(1, 5))
    return np.array([draw(vec3()) for _ in range(n)])


def assert_pose_close(a: Pose, b: Pose, tol: float = TOL) -> None:
    np.testing.assert_allclose(a.R, b.R, atol=tol, rtol=0)
    np.testing.assert_allclose(a.t, b.t, atol=tol * max(1.0, float(np.abs(b.t).max())), rtol=0)


# ---- composition and inverse ------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(poses())
def test_compose_with_inverse_is_identity(a: Pose) -> None:
    assert_pose_close(a @ a.inverse(), Pose.identity())
    assert_pose_close(a.inverse() @ a, Pose.identity())
    assert_pose_close(a.inverse().inverse(), a)


@settings(max_examples=40, deadline=None)
@given(poses(), poses(), poses())
def test_composition_is_associative(a: Pose, b: Pose, c: Pose) -> None:
    assert_pose_close((a @ b) @ c, a @ (b @ c), tol=1e-8)


@settings(max_examples=40, deadline=None)
@given(poses(), poses(), points())
def test_composition_reads_right_to_left(c_from_b: Pose, b_from_a: Pose, X_a: np.ndarray) -> None:
    """``c_from_a = c_from_b @ b_from_a``: apply ``b_from_a`` first."""
    c_from_a = c_from_b @ b_from_a
    expected = c_from_b.transform(b_from_a.transform(X_a))
    scale = max(1.0, np.abs(expected).max())
    np.testing.assert_allclose(c_from_a.transform(X_a), expected, atol=1e-8 * scale)


@settings(max_examples=40, deadline=None)
@given(poses(), points())
def test_transform_is_R_x_plus_t_and_inverse_undoes_it(b_from_a: Pose, X_a: np.ndarray) -> None:
    X_b = b_from_a.transform(X_a)
    scale = max(1.0, np.abs(X_b).max())
    np.testing.assert_allclose(X_b, (b_from_a.R @ X_a.T).T + b_from_a.t, atol=1e-12 * scale)
    np.testing.assert_allclose(b_from_a.inverse().transform(X_b), X_a, atol=1e-9 * scale)


def test_identity() -> None:
    ident = Pose.identity()
    np.testing.assert_array_equal(ident.R, np.eye(3))
    np.testing.assert_array_equal(ident.t, np.zeros(3))


def test_transform_rejects_a_single_point_without_batch_dimension() -> None:
    with pytest.raises(ValueError, match=r"expected shape \(N, 3\)"):
        Pose.identity().transform(np.zeros(3))


# ---- camera centre ----------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(poses())
def test_center_is_minus_Rt_t_and_maps_to_the_origin(cam_from_world: Pose) -> None:
    c = cam_from_world.center
    np.testing.assert_allclose(c, -cam_from_world.R.T @ cam_from_world.t, atol=1e-12)
    # The camera centre (world coordinates) is the origin of the camera frame.
    scale = max(1.0, np.abs(c).max())
    np.testing.assert_allclose(cam_from_world.transform(c[None])[0], 0.0, atol=1e-9 * scale)
    # ... and it is the translation of the inverse pose (world_from_cam).
    np.testing.assert_allclose(cam_from_world.inverse().t, c, atol=1e-12 * max(1.0, np.abs(c).max()))
    assert_pose_close(Pose.from_center(cam_from_world.R, c), cam_from_world)


def test_center_of_docstring_example() -> None:
    cam_from_world = Pose.from_quat_wxyz([1, 0, 0, 0], [0, 0, 2])
    np.testing.assert_array_equal(cam_from_world.center, [0.0, 0.0, -2.0])


# ---- quaternions ------------------------------------------------------------------------------


@settings(max_examples=50, deadline=None)
@given(quats(), vec3())
def test_quaternion_round_trip_and_sign(q: np.ndarray, t: np.ndarray) -> None:
    p = Pose.from_quat_wxyz(q, t)
    q_out = p.quat_wxyz
    assert q_out[0] >= 0.0
    np.testing.assert_allclose(np.linalg.norm(q_out), 1.0, atol=1e-12)
    # q and -q are the same rotation; the output picks the sign with w >= 0.
    sign = 1.0 if q[0] > 0 else -1.0
    if abs(q[0]) > 1e-6:
        np.testing.assert_allclose(q_out, sign * q, atol=1e-9)
    assert_pose_close(Pose.from_quat_wxyz(-q, t), p)
    assert_pose_close(Pose.from_quat_wxyz(q_out, t), p)


@settings(max_examples=40, deadline=None)
@given(quats(), st.floats(0.1, 10.0), vec3())
def test_quaternion_is_normalised_on_input(q: np.ndarray, scale: float, t: np.ndarray) -> None:
    assert_pose_close(Pose.from_quat_wxyz(scale * q, t), Pose.from_quat_wxyz(q, t))


def test_quaternion_order_is_w_x_y_z_hamilton() -> None:
    """(w, x, y, z) = (cos 45°, 0, 0, sin 45°) is +90° about z: it maps x to y (active rotation)."""
    s = np.sqrt(0.5)
    p = Pose.from_quat_wxyz([s, 0.0, 0.0, s], np.zeros(3))
    np.testing.assert_allclose(p.R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(p.R, Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix(), atol=1e-15)
    np.testing.assert_allclose(p.quat_wxyz, [s, 0.0, 0.0, s], atol=1e-15)


def test_zero_quaternion_is_rejected() -> None:
    with pytest.raises(ValueError, match="zero quaternion"):
        Pose.from_quat_wxyz([0.0, 0.0, 0.0, 0.0], np.zeros(3))


@pytest.mark.parametrize("bad", [[1.0, 0.0, 0.0], [np.nan, 0.0, 0.0, 1.0]])
def test_bad_quaternion_input_is_rejected(bad) -> None:
    with pytest.raises(ValueError, match="quat_wxyz"):
        Pose.from_quat_wxyz(bad, np.zeros(3))


# ---- matrices ---------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(poses())
def test_from_matrix_round_trip(p: Pose) -> None:
    assert p.matrix.shape == (3, 4) and p.matrix4.shape == (4, 4)
    np.testing.assert_array_equal(p.matrix4[3], [0.0, 0.0, 0.0, 1.0])
    assert_pose_close(Pose.from_matrix(p.matrix), p, tol=1e-15)
    assert_pose_close(Pose.from_matrix(p.matrix4), p, tol=1e-15)
    # Composition is the matrix product of the homogeneous matrices.
    scale = max(1.0, np.abs(p.t).max())
    np.testing.assert_allclose((p @ p).matrix4, p.matrix4 @ p.matrix4, atol=1e-9 * scale)


def test_from_matrix_rejects_bad_shapes_and_last_row() -> None:
    with pytest.raises(ValueError, match=r"\(3, 4\) or \(4, 4\)"):
        Pose.from_matrix(np.eye(3))
    T = np.eye(4)
    T[3, 0] = 1.0
    with pytest.raises(ValueError, match="last row"):
        Pose.from_matrix(T)


@pytest.mark.parametrize(
    "R",
    [
        np.diag([1.0, 1.0, -1.0]),  # reflection, det = -1
        2.0 * np.eye(3),  # scaled
        np.eye(3) + 1e-3,  # not orthonormal
        np.zeros((3, 3)),
    ],
    ids=["reflection", "scaled", "skewed", "zero"],
)
def test_non_rotation_is_rejected(R: np.ndarray) -> None:
    with pytest.raises(ValueError, match="not a rotation matrix"):
        Pose(R, np.zeros(3))
    with pytest.raises(ValueError):
        Pose.from_matrix(np.hstack([R, np.zeros((3, 1))]))


def test_invalid_input_errors_are_input_errors_with_shapes() -> None:
    with pytest.raises(InputError, match=r"Pose.t: expected shape \(3,\), got \(2,\)"):
        Pose(np.eye(3), np.zeros(2))
    with pytest.raises(InputError, match=r"Pose.R: expected shape \(3, 3\)"):
        Pose(np.eye(4), np.zeros(3))
    with pytest.raises(InputError, match="NaN or inf"):
        Pose(np.eye(3), [0.0, np.inf, 0.0])


def test_pose_is_immutable() -> None:
    p = Pose.identity()
    with pytest.raises(ValueError):
        p.t[0] = 1.0
    with pytest.raises(AttributeError):
        p.t = np.ones(3)  # type: ignore[misc]


def test_constructing_a_pose_leaves_the_callers_arrays_writeable() -> None:
    R, t = np.eye(3), np.zeros(3)
    Pose(R, t)
    t += 1.0  # raises "output array is read-only" with the bug
    assert R.flags.writeable


# ---- error metrics ----------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(poses(), st.floats(0.01, 3.0), vec3())
def test_rotation_error_and_pose_errors(p: Pose, angle: float, axis: np.ndarray) -> None:
    if np.linalg.norm(axis) < 1e-3:
        axis = np.array([0.0, 1.0, 0.0])
    dR = Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)).as_matrix()
    q = Pose(dR @ p.R, p.t)
    assert rotation_error_deg(q.R, p.R) == pytest.approx(np.degrees(angle), abs=1e-6)
    pos_err, rot_err = pose_errors(q, p)
    assert pos_err == pytest.approx(np.linalg.norm(q.center - p.center), abs=1e-9)
    assert rot_err == pytest.approx(np.degrees(angle), abs=1e-6)


# ---- file-format one-liners of docs/conventions.md --------------------------------------------


@settings(max_examples=20, deadline=None)
@given(poses())
def test_conventions_md_format_formulas_round_trip(p: Pose) -> None:
    # TUM 'tx ty tz qx qy qz qw' (camera-to-world).
    w = p.inverse()
    tx, ty, tz, qx, qy, qz, qw = (*w.t, *w.quat_wxyz[[1, 2, 3, 0]])
    assert_pose_close(Pose.from_quat_wxyz([qw, qx, qy, qz], [tx, ty, tz]).inverse(), p, tol=1e-9)
    # KITTI 12 numbers, row-major camera-to-world [R | c].
    v = p.inverse().matrix.ravel()
    assert_pose_close(Pose.from_matrix(np.reshape(v, (3, 4))).inverse(), p, tol=1e-9)
    np.testing.assert_allclose(v[[3, 7, 11]], p.center, atol=1e-12 * max(1.0, np.abs(p.center).max()))
    # COLMAP / hloc 'qw qx qy qz tx ty tz' (world-to-camera).
    qw, qx, qy, qz, tx, ty, tz = (*p.quat_wxyz, *p.t)
    assert_pose_close(Pose.from_quat_wxyz([qw, qx, qy, qz], [tx, ty, tz]), p, tol=1e-12)


def test_conventions_md_formulas_match_the_readers(tmp_path) -> None:
    from planarloc.io.pose_list import format_pose_line
    from planarloc.io.tum import read_tum_trajectory

    p = Pose.from_quat_wxyz([0.9, 0.1, -0.2, 0.3], [1.0, 2.0, 3.0])
    w = p.inverse()
    line = " ".join(f"{v:.17g}" for v in (0.0, *w.t, *w.quat_wxyz[[1, 2, 3, 0]]))
    (tmp_path / "gt.txt").write_text(line + "\n")
    _, (world_from_cam,) = read_tum_trajectory(tmp_path / "gt.txt")
    assert_pose_close(world_from_cam.inverse(), p, tol=1e-12)
    values = np.array(format_pose_line("q.png", p).split()[1:], dtype=float)
    np.testing.assert_allclose(values, [*p.quat_wxyz, *p.t], atol=1e-15)
