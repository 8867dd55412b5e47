"""Match plots: inliers and outliers drawn in their colours, caption with the error, unscored pairs."""

from __future__ import annotations

import cv2
import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.robust.pair_matches import PairMatches
from planarloc.robust.result import PoseEstimate
from planarloc.viz.matches import estimate_caption, match_plot_name, save_match_plot

CAMERA = Camera("PINHOLE", 160, 120, (100.0, 100.0, 80.0, 60.0))


def _pixels(path, bgr, tol=40):
    img = cv2.imread(str(path)).astype(int)
    return int((np.abs(img - np.array(bgr)).sum(axis=2) < tol).sum())


def test_inliers_green_outliers_red_and_unscored(tmp_path):
    rng = np.random.default_rng(0)
    for k, name in enumerate(("q.png", "r0.png", "r1.png")):
        cv2.imwrite(str(tmp_path / name), np.full((120, 160, 3), 255, np.uint8))  # white: only lines are coloured
    pts = rng.uniform([5, 5], [155, 115], size=(40, 2))
    pair = PairMatches(Pose.identity(), CAMERA, pts, pts + 1.0)
    truth = Pose.from_quat_wxyz([1, 0, 0, 0], [0.1, 0, 0])
    est = PoseEstimate(Pose.identity(), True, "success", "", [np.arange(40) < 30, np.zeros(40, bool)],
                       num_inliers=30, references=["r0.png", "r1.png"])
    all_in = save_match_plot(tmp_path / "a.png", tmp_path / "q.png", [tmp_path / "r0.png", tmp_path / "r1.png"],
                             [pair, pair], [np.ones(40, bool), np.ones(40, bool)], est, "q.png", truth)
    none_in = save_match_plot(tmp_path / "b.png", tmp_path / "q.png", [tmp_path / "r0.png", tmp_path / "r1.png"],
                              [pair, pair], [None, np.zeros(40, bool)], est, "q.png", None)
    green, red = (80, 152, 26), (39, 48, 215)  # BGR of the plot colours
    assert _pixels(all_in, green) > 500 and _pixels(all_in, red) < 50
    assert _pixels(none_in, red) > 500 and _pixels(none_in, green) < 50
    assert "error 0.100 m / 0.00°" in estimate_caption("q.png", est, truth)
    assert "no ground truth" in estimate_caption("q.png", est, None)
    failed = PoseEstimate(None, False, "too_few_matches", "", [], references=[])
    assert "error" not in estimate_caption("q", failed, truth)
    assert save_match_plot(tmp_path / "c.png", tmp_path / "q.png", [], [], [], failed, "q").is_file()
    assert match_plot_name("cam/0.5.png") == "cam__0.5.png"
