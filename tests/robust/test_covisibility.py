"""Whether a map image sees the query: the epipolar support of real views against chance."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.robust.covisibility import epipolar_support, seeing_support

CAM = Camera.from_K([[400.0, 0, 320], [0, 400.0, 240], [0, 0, 1]], 640, 480)
OTHER = Camera.from_K([[300.0, 0, 160], [0, 310.0, 120], [0, 0, 1]], 320, 240)


def two_views(n: int, rng: np.random.Generator, noise_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) pixels of random points seen by CAM at the origin and by OTHER moved and turned."""
    X = rng.uniform([-3, -2, 4], [3, 2, 12], (n, 3))
    ref = Pose(
        Pose.from_quat_wxyz([np.cos(0.1), 0, np.sin(0.1), 0], np.zeros(3)).R, np.array([0.8, 0.05, -0.3])
    )
    q = CAM.img_from_cam(X) + rng.normal(0, noise_px, (n, 2))
    r = OTHER.img_from_cam((ref.R @ X.T).T + ref.t) + rng.normal(0, noise_px, (n, 2))
    return q, r


@pytest.mark.parametrize("n", [20, 60, 300])
def test_two_real_views_see_each_other(n: int) -> None:
    rng = np.random.default_rng(n)
    q, r = two_views(n, rng, noise_px=0.3)
    support = epipolar_support(q, r, CAM, OTHER)
    assert support >= 0.9 * n and support >= seeing_support(n)
    # with 70 % of the matches wrong, the 30 % right ones still show the view
    k = int(0.7 * n)
    r_bad = r.copy()
    r_bad[:k] = rng.uniform([0, 0], [320, 240], (k, 2))
    if n - k >= seeing_support(n):
        assert epipolar_support(q, r_bad, CAM, OTHER) >= seeing_support(n)


@pytest.mark.parametrize("n", [8, 30, 120, 400])
def test_random_matches_never_see(n: int) -> None:
    rng = np.random.default_rng(1000 + n)
    for _ in range(15):
        q = rng.uniform([0, 0], [640, 480], (n, 2))
        r = rng.uniform([0, 0], [320, 240], (n, 2))
        assert epipolar_support(q, r, CAM, OTHER) < seeing_support(n)


def test_the_count_is_deterministic_and_bad_input_is_refused() -> None:
    rng = np.random.default_rng(5)
    q, r = two_views(100, rng, noise_px=2.0)
    assert epipolar_support(q, r, CAM, OTHER) == epipolar_support(q, r, CAM, OTHER)
    assert epipolar_support(q[:4], r[:4], CAM, OTHER) == 0
    with pytest.raises(InputError):
        epipolar_support(q, r[:-1], CAM, OTHER)
    with pytest.raises(InputError):
        epipolar_support(np.full((10, 2), np.nan), r[:10], CAM, OTHER)


def test_a_degenerate_set_has_no_support_instead_of_an_opencv_error() -> None:
    """Repeated points (a warm-up on a map image's own features can give them) have no essential
    matrix: support 0, not OpenCV's solvePoly error."""
    q = np.tile([[100.0, 80.0]], (30, 1))
    r = np.tile([[150.0, 90.0]], (30, 1))
    assert epipolar_support(q, r, CAM, OTHER) == 0
