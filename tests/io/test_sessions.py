"""Several sessions as one map: unique names, labels, cache path."""

from __future__ import annotations

import numpy as np

from planarloc.io.pose_list import write_pose_list
from planarloc.io.sessions import read_sessions, session_labels, sessions_map_path


def write_session(root, write_image, random_poses, n, seed):
    names = [f"img/{k}.png" for k in range(n)]
    for name in names:
        write_image(root / name)
    write_pose_list(root / "poses.txt", list(zip(names, random_poses(n, seed))))
    (root / "cameras.txt").write_text("PINHOLE 8 6 10 10 4 3\n")
    return root


def test_two_sessions_get_prefixed_unique_names(tmp_path, write_image, random_poses):
    a = write_session(tmp_path / "x" / "home1", write_image, random_poses, 3, 0)
    b = write_session(tmp_path / "y" / "home1", write_image, random_poses, 2, 1)
    one = read_sessions([a], "list")
    assert [im.name for im in one] == ["img/0.png", "img/1.png", "img/2.png"]
    both = read_sessions([a, b], "list")
    assert [im.name for im in both] == [
        "home1/img/0.png",
        "home1/img/1.png",
        "home1/img/2.png",
        "home1-2/img/0.png",
        "home1-2/img/1.png",
    ]
    np.testing.assert_allclose(both[3].cam_from_world.matrix4, random_poses(2, 1)[0].matrix4, atol=1e-12)
    (tmp_path / "run.bag").write_bytes(b"")
    assert session_labels([a, b, tmp_path / "run.bag"]) == ["home1", "home1-2", "run"]
    p1 = sessions_map_path([a, b], "list", {}, "f")
    assert p1 != sessions_map_path([a], "list", {}, "f") and p1 != sessions_map_path(
        [a, b], "list", {"k": 1}, "f"
    )
    assert p1.name.startswith("home1+home1-2-")
