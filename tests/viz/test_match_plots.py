"""Match plots: inliers and outliers drawn in their colours, caption with the error, unscored pairs; a
subsample of the match lines, inliers on top."""

from __future__ import annotations

import cv2
import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.robust.pair_matches import PairMatches
from planarloc.robust.result import PoseEstimate
from planarloc.viz.matches import (
    INLIER_COLOR,
    OUTLIER_COLOR,
    estimate_caption,
    lines_to_draw,
    match_plot_name,
    plot_pair,
    save_match_plot,
)

CAMERA = Camera("PINHOLE", 160, 120, (100.0, 100.0, 80.0, 60.0))


def _pixels(path, bgr, tol=40):
    img = cv2.imread(str(path)).astype(int)
    return int((np.abs(img - np.array(bgr)).sum(axis=2) < tol).sum())


def test_inliers_green_outliers_red_and_unscored(tmp_path):
    rng = np.random.default_rng(0)
    for k, name in enumerate(("q.png", "r0.png", "r1.png")):
        cv2.imwrite(
            str(tmp_path / name), np.full((120, 160, 3), 255, np.uint8)
        )  # white: only lines are coloured
    pts = rng.uniform([5, 5], [155, 115], size=(40, 2))
    pair = PairMatches(Pose.identity(), CAMERA, pts, pts + 1.0)
    truth = Pose.from_quat_wxyz([1, 0, 0, 0], [0.1, 0, 0])
    est = PoseEstimate(
        Pose.identity(),
        True,
        "success",
        "",
        [np.arange(40) < 30, np.zeros(40, bool)],
        num_inliers=30,
        references=["r0.png", "r1.png"],
    )
    all_in = save_match_plot(
        tmp_path / "a.png",
        tmp_path / "q.png",
        [tmp_path / "r0.png", tmp_path / "r1.png"],
        [pair, pair],
        [np.ones(40, bool), np.ones(40, bool)],
        est,
        "q.png",
        truth,
    )
    none_in = save_match_plot(
        tmp_path / "b.png",
        tmp_path / "q.png",
        [tmp_path / "r0.png", tmp_path / "r1.png"],
        [pair, pair],
        [None, np.zeros(40, bool)],
        est,
        "q.png",
        None,
    )
    green, red = (80, 152, 26), (39, 48, 215)  # BGR of the plot colours
    assert _pixels(all_in, green) > 500 and _pixels(all_in, red) < 50
    assert _pixels(none_in, red) > 500 and _pixels(none_in, green) < 50
    assert "error 0.100 m / 0.00°" in estimate_caption("q.png", est, truth)
    assert "no ground truth" in estimate_caption("q.png", est, None)
    failed = PoseEstimate(None, False, "too_few_matches", "", [], references=[])
    assert "error" not in estimate_caption("q", failed, truth)
    assert save_match_plot(tmp_path / "c.png", tmp_path / "q.png", [], [], [], failed, "q").is_file()
    assert match_plot_name("cam/0.5.png") == "cam__0.5.png"


def test_lines_to_draw_is_a_seeded_subsample_that_prefers_inliers() -> None:
    inl = np.arange(500) < 400  # 400 inliers, 100 outliers
    out, keep = lines_to_draw(inl, max_lines=100, seed=3)
    assert (len(out), len(keep)) == (25, 75)  # outliers keep a quarter when inliers would fill it
    assert inl[keep].all() and not inl[out].any() and len(set(keep)) == 75
    assert all(np.array_equal(a, b) for a, b in zip((out, keep), lines_to_draw(inl, max_lines=100, seed=3)))
    out, keep = lines_to_draw(
        np.arange(500) < 30, max_lines=100
    )  # few inliers: all of them, outliers fill up
    assert (len(out), len(keep)) == (70, 30)
    out, keep = lines_to_draw(np.ones(40, bool), max_lines=100)  # fewer matches than lines: every one
    assert (len(out), len(keep)) == (0, 40)
    assert [len(a) for a in lines_to_draw(np.zeros(10, bool), max_lines=0)] == [0, 0]


def test_a_pair_draws_at_most_max_lines_outliers_first_and_says_so() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.colors import to_rgba

    rng = np.random.default_rng(0)
    pts = rng.uniform([5, 5], [155, 115], size=(600, 2))
    pair = PairMatches(Pose.identity(), CAMERA, pts, pts + 1.0)
    inl = np.arange(600) < 450
    img = np.full((120, 160, 3), 255, np.uint8)
    fig, ax = plt.subplots()
    plot_pair(ax, img, img, pair, inl, "r0.png", max_lines=80)
    lines = [c for c in ax.collections if isinstance(c, LineCollection)]
    assert sum(len(c.get_segments()) for c in lines) <= 80
    outliers, inliers = lines  # outliers added first ...
    assert np.allclose(outliers.get_colors()[0][:3], to_rgba(OUTLIER_COLOR)[:3])
    assert np.allclose(inliers.get_colors()[0][:3], to_rgba(INLIER_COLOR)[:3])
    assert inliers.get_zorder() > outliers.get_zorder()  # ... inliers on top
    assert (
        outliers.get_linewidths()[0] <= inliers.get_linewidths()[0]
        and outliers.get_alpha() < inliers.get_alpha()
    )
    assert (len(outliers.get_segments()), len(inliers.get_segments())) == (20, 60)
    assert "lines for 60 of 450 inliers, 20 of 150 outliers" in ax.get_title()
    dots = [c for c in ax.collections if not isinstance(c, LineCollection)]
    assert sum(len(c.get_offsets()) for c in dots) == 2 * 600  # every match keeps its dots
    plt.close(fig)
