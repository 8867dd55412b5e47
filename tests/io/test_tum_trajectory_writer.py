"""TUM trajectory writer: round trip through our reader and evo's, and its errors."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.validation import InputError
from planarloc.io.tum import read_tum_trajectory, write_tum_trajectory


def test_round_trip_through_our_reader_and_evo(tmp_path, random_poses):
    poses = random_poses(4, 7)
    times = np.array([1305031102.175304, 1305031102.211214, 1305031102.243211, 1305031102.5])
    path = tmp_path / "sub" / "estimate.txt"
    write_tum_trajectory(path, times, poses)
    t, back = read_tum_trajectory(path)
    np.testing.assert_allclose(t, times, atol=1e-6)
    for a, b in zip(back, poses):
        np.testing.assert_allclose(a.matrix4, b.matrix4, atol=1e-8)
    file_interface = pytest.importorskip("evo.tools.file_interface")
    traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_allclose(traj.positions_xyz, [p.t for p in poses], atol=1e-8)
    np.testing.assert_allclose(traj.poses_se3[2][:3, :3], poses[2].R, atol=1e-8)


def test_timestamps_must_increase_and_match(tmp_path, random_poses):
    poses = random_poses(2, 0)
    with pytest.raises(InputError, match="strictly increasing"):
        write_tum_trajectory(tmp_path / "a.txt", [1.0, 1.0], poses)
    with pytest.raises(InputError, match="3 timestamps for 2 poses"):
        write_tum_trajectory(tmp_path / "a.txt", [1.0, 2.0, 3.0], poses)
    assert not (tmp_path / "a.txt").exists()
