"""Rigid transforms. The one pose type of planarloc.

Convention (see ``docs/conventions.md``): a :class:`Pose` named ``b_from_a`` maps points of
frame ``a`` to frame ``b``: ``x_b = R @ x_a + t``. Camera poses are ``cam_from_world`` as in
COLMAP/pycolmap. Composition reads right to left: ``c_from_a = c_from_b @ b_from_a``.
Quaternions are Hamilton, scalar first: ``quat_wxyz = (w, x, y, z)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from planarloc.geometry.validation import check_array, check_rotation


@dataclass(frozen=True, eq=False)
class Pose:
    """A rigid transform ``b_from_a``: ``x_b = R @ x_a + t``.

    Attributes:
        R: (3, 3) rotation matrix, validated to be orthonormal with det +1.
        t: (3,) translation, in the units of frame ``b`` (metres for camera poses).

    Example:
        >>> cam_from_world = Pose.from_quat_wxyz([1, 0, 0, 0], [0, 0, 2])
        >>> cam_from_world.center          # camera centre in world coordinates
        array([ 0.,  0., -2.])
    """

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        R = check_rotation("Pose.R", self.R).copy()  # never freeze the caller's arrays
        t = check_array("Pose.t", self.t, (3,)).copy()
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    # ---- constructors -------------------------------------------------------------------
    @classmethod
    def _unchecked(cls, R: np.ndarray, t: np.ndarray) -> Pose:
        """Internal: a pose from a rotation and translation that are valid by construction
        (solver output, composition or inverse of validated poses), without re-validating
        them. ~1 µs instead of ~15 µs; public constructors validate."""
        obj = object.__new__(cls)
        R = np.array(R, dtype=np.float64, order="C")  # C order even for a transposed view (inverse)
        t = np.array(t, dtype=np.float64, order="C")
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(obj, "R", R)
        object.__setattr__(obj, "t", t)
        return obj

    @classmethod
    def _from_buffer(cls, buf: np.ndarray, n: int) -> list[Pose]:
        """Internal: the first ``n`` poses of a fresh (K, 4, 3) solver output buffer, no copies.

        Pose ``k`` is ``R = buf[k, :3]``, ``t = buf[k, 3]`` (views). The caller hands the buffer
        over: it must hold valid poses by construction and nobody else may keep a reference.
        It is made read-only once, so the poses stay immutable. ~0.3 µs per pose.
        """
        if n < 0:
            raise ValueError(f"Pose._from_buffer: negative count {n} (an unhandled solver error code)")
        if n == 0:
            return []
        buf.setflags(write=False)
        new = object.__new__
        poses = []
        for k in range(n):
            pose = new(cls)
            fields = pose.__dict__  # frozen dataclass: bypass __setattr__ as __post_init__ does
            fields["R"] = buf[k, :3]
            fields["t"] = buf[k, 3]
            poses.append(pose)
        return poses

    @classmethod
    def identity(cls) -> Pose:
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_quat_wxyz(cls, quat_wxyz: object, t: object) -> Pose:
        """From a (w, x, y, z) quaternion (normalised here; must not be zero) and translation."""
        q = check_array("quat_wxyz", quat_wxyz, (4,))
        n = np.linalg.norm(q)
        if n < 1e-12:
            raise ValueError("quat_wxyz: zero quaternion does not describe a rotation")
        R = Rotation.from_quat(q[[1, 2, 3, 0]] / n).as_matrix()
        return cls(R, check_array("t", t, (3,)))

    @classmethod
    def from_matrix(cls, T: object) -> Pose:
        """From a (3, 4) ``[R | t]`` or (4, 4) homogeneous matrix."""
        T = check_array("T", T)
        if T.shape not in ((3, 4), (4, 4)):
            raise ValueError(f"T: expected shape (3, 4) or (4, 4), got {T.shape}")
        if T.shape == (4, 4) and not np.allclose(T[3], [0, 0, 0, 1]):
            raise ValueError(f"T: last row of a homogeneous matrix must be [0, 0, 0, 1], got {T[3]}")
        return cls(T[:3, :3], T[:3, 3])

    @classmethod
    def from_center(cls, R: object, center: object) -> Pose:
        """``cam_from_world`` from its rotation and the camera centre in world coordinates."""
        R = check_rotation("R", R)
        c = check_array("center", center, (3,))
        return cls(R, -R @ c)

    # ---- derived quantities ----------------------------------------------------------------
    @property
    def quat_wxyz(self) -> np.ndarray:
        """(4,) unit quaternion (w, x, y, z) of ``R`` with w >= 0."""
        x, y, z, w = Rotation.from_matrix(self.R).as_quat()
        q = np.array([w, x, y, z])
        return -q if w < 0 else q

    @property
    def center(self) -> np.ndarray:
        """(3,) origin of frame ``b`` expressed in frame ``a``, i.e. ``-Rᵀ t``.

        For ``cam_from_world`` this is the camera centre in world coordinates.
        """
        return -self.R.T @ self.t

    @property
    def matrix(self) -> np.ndarray:
        """(3, 4) ``[R | t]``."""
        return np.hstack([self.R, self.t[:, None]])

    @property
    def matrix4(self) -> np.ndarray:
        """(4, 4) homogeneous matrix."""
        T = np.eye(4)
        T[:3, :4] = self.matrix
        return T

    def inverse(self) -> Pose:
        """``a_from_b`` for ``self = b_from_a``."""
        return Pose._unchecked(self.R.T, -self.R.T @ self.t)

    def transform(self, points: object) -> np.ndarray:
        """Map (N, 3) points of frame ``a`` to frame ``b``."""
        X = check_array("points", points, (None, 3))
        return X @ self.R.T + self.t

    def __matmul__(self, other: Pose) -> Pose:
        """``c_from_a = c_from_b @ b_from_a``."""
        if not isinstance(other, Pose):
            return NotImplemented
        return Pose._unchecked(self.R @ other.R, self.R @ other.t + self.t)

    def __repr__(self) -> str:
        q = np.array2string(self.quat_wxyz, precision=6, separator=", ")
        t = np.array2string(self.t, precision=6, separator=", ")
        return f"Pose(quat_wxyz={q}, t={t})"


def rotation_error_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of ``R_a R_bᵀ`` in degrees: ``arccos((tr(R_a R_bᵀ) - 1) / 2)`` (paper Sec. V-A)."""
    c = (np.trace(R_a @ R_b.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def pose_errors(estimate: Pose, truth: Pose) -> tuple[float, float]:
    """(position error of the camera centre in metres, rotation error in degrees).

    The paper (Sec. V-A) uses ``|t - t_gt|``; for ``cam_from_world`` poses with equal rotation
    the two differ only by the rotation error, so we report the centre distance, which is what
    users mean by localization error.
    """
    return float(np.linalg.norm(estimate.center - truth.center)), rotation_error_deg(estimate.R, truth.R)
