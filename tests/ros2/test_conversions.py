"""ROS conversions of the node, without ROS: cameras from CameraInfo, covariances in ROS order,
odometry at an image's stamp, the transform tree and AMCL's map -> odom."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.localize.sequence import ros_covariance
from planarloc.robust.pose_graph import so3_exp, so3_log
from planarloc.ros2.conversions import (
    OdometryBuffer,
    TransformTree,
    camera_from_camera_info,
    map_from_odom,
    map_from_world_from_gravity,
    map_pose_of_child,
    ros_covariance_of_child,
    ros_covariance_of_parent,
    stamp_parts,
)


def _info(model: str, d: list[float], w: int = 640, h: int = 480) -> SimpleNamespace:
    k = [500.0, 0.0, 320.0, 0.0, 510.0, 240.0, 0.0, 0.0, 1.0]
    p = [480.0, 0.0, 318.0, 0.0, 0.0, 480.0, 242.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    return SimpleNamespace(width=w, height=h, k=k, p=p, d=d, distortion_model=model)


@pytest.mark.parametrize(
    "model, d, expected",
    [
        (
            "plumb_bob",
            [0.1, -0.05, 0.001, 0.002, 0.0],
            Camera("OPENCV", 640, 480, (500, 510, 320, 240, 0.1, -0.05, 0.001, 0.002)),
        ),
        ("plumb_bob", [0.0] * 5, Camera("PINHOLE", 640, 480, (500, 510, 320, 240))),
        (
            "rational_polynomial",
            [0.1, -0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            Camera("OPENCV", 640, 480, (500, 510, 320, 240, 0.1, -0.05, 0.0, 0.0)),
        ),
        (
            "equidistant",
            [0.01, -0.02, 0.003, -0.001],
            Camera("OPENCV_FISHEYE", 640, 480, (500, 510, 320, 240, 0.01, -0.02, 0.003, -0.001)),
        ),
        ("equidistant", [0.0] * 4, Camera("OPENCV_FISHEYE", 640, 480, (500, 510, 320, 240, 0, 0, 0, 0))),
    ],
)
def test_camera_info_models(model: str, d: list[float], expected: Camera) -> None:
    assert camera_from_camera_info(_info(model, d)) == expected


def test_rectified_topics_use_the_projection_matrix() -> None:
    cam = camera_from_camera_info(_info("equidistant", [0.01, 0, 0, 0]), rectified=True)
    assert cam == Camera("PINHOLE", 640, 480, (480, 480, 318, 242))


@pytest.mark.parametrize(
    "model, d, message",
    [
        ("plumb_bob", [0.1, 0.0, 0.0, 0.0, 0.02], "not supported"),
        ("rational_polynomial", [0.1, 0, 0, 0, 0, 0.3, 0, 0], "not supported"),
        ("equidistant", [0.1, 0.0], "4 coefficients"),
    ],
)
def test_unsupported_camera_info_is_an_error(model: str, d: list[float], message: str) -> None:
    with pytest.raises(InputError, match=message):
        camera_from_camera_info(_info(model, d))


def _random_pose(rng: np.random.Generator) -> Pose:
    return Pose(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))


def _ros_vector(parent_from_child: Pose, reference: Pose) -> np.ndarray:
    """ROS-order perturbation (δp, φ about the parent's axes) of ``parent_from_child`` from ``reference``."""
    return np.concatenate(
        [parent_from_child.t - reference.t, so3_log((parent_from_child.R @ reference.R.T)[None])[0]]
    )


def test_stream_covariance_in_ros_order_matches_a_numeric_jacobian() -> None:
    """The stream's (ω, δc) of cam_from_world, mapped through the poses themselves, gives the
    conversion's covariance for the camera and for a base mounted below it."""
    rng = np.random.default_rng(3)
    cam_from_world = _random_pose(rng)
    base_from_camera = _random_pose(rng)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T * 1e-3
    eps = 1e-6

    def perturbed(x: np.ndarray) -> Pose:  # the stream's tangent space: R = Exp(ω) R₀, c = c₀ + δc
        R = so3_exp(x[:3])[0] @ cam_from_world.R
        return Pose.from_center(R, cam_from_world.center + x[3:])

    for camera_from_child in (Pose.identity(), base_from_camera.inverse()):
        reference = cam_from_world.inverse() @ camera_from_child
        J = np.stack(
            [
                (
                    _ros_vector(perturbed(eps * e).inverse() @ camera_from_child, reference)
                    - _ros_vector(perturbed(-eps * e).inverse() @ camera_from_child, reference)
                )
                / (2 * eps)
                for e in np.eye(6)
            ],
            axis=1,
        )
        expected = J @ cov @ J.T
        ros = ros_covariance(cam_from_world, cov)
        got = ros_covariance_of_child(cam_from_world.inverse(), ros, camera_from_child)
        assert np.allclose(got, expected, rtol=1e-5, atol=1e-12)
        # the published pose in a z-up map: the same perturbations seen through map_from_world
        map_from_world = map_from_world_from_gravity(rng.normal(size=3))
        J = np.stack(
            [
                (
                    _ros_vector(
                        map_from_world @ perturbed(eps * e).inverse() @ camera_from_child,
                        map_from_world @ reference,
                    )
                    - _ros_vector(
                        map_from_world @ perturbed(-eps * e).inverse() @ camera_from_child,
                        map_from_world @ reference,
                    )
                )
                / (2 * eps)
                for e in np.eye(6)
            ],
            axis=1,
        )
        pose, got = map_pose_of_child(cam_from_world.inverse(), ros, camera_from_child, map_from_world)
        assert np.allclose(pose.matrix, (map_from_world @ reference).matrix)
        assert np.allclose(got, J @ cov @ J.T, rtol=1e-5, atol=1e-12)
    # the position block of the camera's is the stream's centre block: position_std_m is its worst axis
    assert np.allclose(ros_covariance(cam_from_world, cov)[:3, :3], cov[3:, 3:])


def test_map_from_world_puts_gravity_along_minus_z_and_keeps_the_world_x_in_the_ground_plane() -> None:
    rng = np.random.default_rng(4)
    for g in [
        *rng.normal(size=(200, 3)),
        (0.0, 0.0, -1.0),
        (0.0, 1.0, 0.0),
        (1.0, 0.0, 0.0),
        (-0.8, 0.6, 0.0),
    ]:
        R = map_from_world_from_gravity(3.0 * np.asarray(g)).R
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(R @ (np.asarray(g) / np.linalg.norm(g)), [0, 0, -1], atol=1e-12)
        up = -np.asarray(g) / np.linalg.norm(g)
        kept = (
            np.eye(3)[0] if abs(up[0]) <= np.sqrt(0.5) else np.eye(3)[1]
        )  # the world axis kept in the map x-z plane
        assert abs((R @ kept)[1]) < 1e-12 and (R @ kept)[0] > 0.7 - 1e-12
    # KITTI / generated worlds (y down, z forward): map x = world x, map y = world z, map z = -world y
    assert np.array_equal(map_from_world_from_gravity([0, 1, 0]).R, [[1, 0, 0], [0, 0, 1], [0, -1, 0]])
    assert np.allclose(map_from_world_from_gravity([0, 0, -2]).matrix, np.eye(3, 4))  # already z-up: identity
    with pytest.raises(InputError, match="g_world"):
        map_from_world_from_gravity([0, 0, 0])


def test_covariance_in_a_rotated_parent_matches_a_numeric_jacobian() -> None:
    """Both ROS blocks (position, rotation vector about the parent's axes) follow the new parent."""
    rng = np.random.default_rng(5)
    world_from_child, map_from_world = _random_pose(rng), _random_pose(rng)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T * 1e-3
    eps = 1e-6

    def perturbed(x: np.ndarray) -> Pose:  # ROS perturbation in the world: (Exp(φ) R, p + δp)
        return Pose(so3_exp(x[3:])[0] @ world_from_child.R, world_from_child.t + x[:3])

    reference = map_from_world @ world_from_child
    J = np.stack(
        [
            (
                _ros_vector(map_from_world @ perturbed(eps * e), reference)
                - _ros_vector(map_from_world @ perturbed(-eps * e), reference)
            )
            / (2 * eps)
            for e in np.eye(6)
        ],
        axis=1,
    )
    got = ros_covariance_of_parent(map_from_world, cov)
    assert np.allclose(got, J @ cov @ J.T, rtol=1e-5, atol=1e-12)
    assert not np.allclose(got, cov, atol=1e-6)  # the rotation matters


def test_a_non_finite_stream_covariance_stays_non_finite() -> None:
    assert not np.isfinite(ros_covariance(Pose.identity(), np.full((6, 6), np.inf))).any()


def test_odometry_is_interpolated_at_the_image_stamp() -> None:
    buf = OdometryBuffer(horizon_s=5.0)
    a = Pose.identity()
    b = Pose(Rotation.from_euler("z", 20, degrees=True).as_matrix(), [1.0, 0.0, 0.0])
    buf.add(10.2, b)
    buf.add(10.0, a)  # out of order
    mid = buf.at(10.05, tolerance_s=0.1)
    assert np.allclose(mid.t, [0.25, 0, 0]) and np.isclose(
        Rotation.from_matrix(mid.R).as_euler("xyz", True)[2], 5
    )
    assert buf.at(10.25, tolerance_s=0.1) is b  # nearest within the tolerance
    assert buf.at(10.5, tolerance_s=0.1) is None  # none near enough
    buf.add(20.0, a)
    assert buf.stamps == [20.0]  # the horizon forgets old samples
    sparse = OdometryBuffer()
    sparse.add(0.0, a)
    sparse.add(1.0, b)
    assert sparse.at(0.5, tolerance_s=0.1) is None  # samples too far apart to interpolate


def test_transform_tree_chains_and_common_ancestors() -> None:
    rng = np.random.default_rng(1)
    odom_from_base, base_from_mast, mast_from_camera, base_from_imu = (_random_pose(rng) for _ in range(4))
    tree = TransformTree()
    tree.add_many(
        [
            ("odom", "base_link", odom_from_base),
            ("base_link", "mast", base_from_mast),
            ("/mast", "/camera", mast_from_camera),
            ("base_link", "imu", base_from_imu),
        ]
    )
    assert np.allclose(tree.lookup("base_link", "camera").matrix, (base_from_mast @ mast_from_camera).matrix)
    assert np.allclose(
        tree.lookup("imu", "camera").matrix,
        (base_from_imu.inverse() @ base_from_mast @ mast_from_camera).matrix,
    )
    assert np.allclose(tree.lookup("camera", "camera").matrix, np.eye(3, 4))
    assert tree.lookup("base_link", "elsewhere") is None


def test_map_to_odom_follows_the_odometry() -> None:
    rng = np.random.default_rng(2)
    map_from_base, odom_from_base = _random_pose(rng), _random_pose(rng)
    m = map_from_odom(map_from_base, odom_from_base)
    assert np.allclose((m @ odom_from_base).matrix, map_from_base.matrix)


def test_stamp_parts() -> None:
    assert stamp_parts(12.25) == (12, 250_000_000)
    assert stamp_parts(0.999999999999) == (1, 0)
