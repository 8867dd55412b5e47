"""The trajectory plot: the top view lies in the map's gravity plane, with plain axis names; the
colour scale is logarithmic and fits the errors; estimate → truth segments; the error-over-time
panel; localized, predicted and failed results drawn apart; no empty legend entries."""

from __future__ import annotations

from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.collections import LineCollection
from matplotlib.colors import LogNorm

from planarloc.geometry.validation import InputError
from planarloc.viz.trajectory import (
    ERROR_FLOOR_M,
    MIN_ERROR_SPAN,
    axis_labels,
    error_norm,
    format_metres,
    gravity_plane_basis,
    plot_error_over_time,
    plot_localization,
    result_times,
    save_localization_plot,
)


def _result(center, error, success=True, status="success", estimate_offset=None, timestamp=None):
    """A result as the plots read it (the attributes of QueryResult / FrameResult)."""
    center = np.asarray(center, float)
    est = None if estimate_offset is None else tuple(center + np.asarray(estimate_offset, float))
    return SimpleNamespace(
        truth_center=tuple(center),
        success=success,
        translation_error_m=error,
        status=status,
        estimate_center=est,
        timestamp=timestamp,
    )


def _ring(n=12, radius=2.0):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([radius * np.cos(a), np.zeros(n), radius * np.sin(a)], axis=1)  # y down: the x-z plane


@pytest.fixture
def axes():
    fig, ax = plt.subplots()
    yield ax
    plt.close(fig)


@pytest.mark.parametrize(
    "g, ex, ey",
    [
        ((0, 1, 0), (1, 0, 0), (0, 0, 1)),  # y down (KITTI, generated worlds)
        ((0, 0, -1), (1, 0, 0), (0, 1, 0)),  # z up (OpenLORIS)
        ((-2, 0, 0), (0, 1, 0), (0, 0, 1)),
    ],
)  # x up
def test_the_plane_is_perpendicular_to_gravity_seen_from_above(g, ex, ey) -> None:
    bx, by, _ = gravity_plane_basis(g)
    np.testing.assert_allclose(bx, ex, atol=1e-12)
    np.testing.assert_allclose(by, ey, atol=1e-12)
    down = np.asarray(g, float) / np.linalg.norm(g)
    assert np.cross(bx, by) @ -down == pytest.approx(1.0)  # right-handed about "up": a map, not a mirror


def test_a_tilted_gravity_gives_a_tilted_plane() -> None:
    g = np.array([0.0, np.cos(0.2), np.sin(0.2)])
    ex, ey, name = gravity_plane_basis(g)
    assert name == "x" and abs(ex @ g) < 1e-12 and abs(ey @ g) < 1e-12 and abs(ex @ ey) < 1e-12
    with pytest.raises(InputError, match="g_world"):
        gravity_plane_basis([0, 0, 0])


@pytest.mark.parametrize(
    "g, labels",
    [
        ((0, 1, 0), ("world x [m]", "world z [m]")),
        ((0, 0, -1), ("world x [m]", "world y [m]")),
        ((0, -1, 0), ("world x [m]", "−world z [m]")),  # y up: page y is −z
        ((0, 1, 0.05), ("world x [m]", "≈ world z [m]")),
    ],
)  # 2.9° tilt
def test_the_axes_are_named_after_the_world_axes_they_are(g, labels) -> None:
    assert axis_labels(g) == labels


def test_the_plot_draws_the_projection(tmp_path, axes) -> None:
    """A z-up world: the ground truth is drawn at (x, y), whatever its height."""
    truth = [(1.0, 2.0, 5.0), (3.0, -1.0, 7.0)]
    results = [SimpleNamespace(truth_center=c, success=True, translation_error_m=0.1) for c in truth]
    sc = plot_localization(axes, np.zeros((2, 3)), results, g_world=(0, 0, -1))
    np.testing.assert_allclose(sc.get_offsets(), [[1.0, 2.0], [3.0, -1.0]])
    assert (axes.get_xlabel(), axes.get_ylabel()) == ("world x [m]", "world y [m]")
    save_localization_plot(tmp_path / "p.png", np.zeros((2, 3)), results, "t", g_world=(0, 0, -1))
    assert (tmp_path / "p.png").stat().st_size > 1000


def test_the_colour_scale_is_logarithmic_and_spans_the_errors() -> None:
    norm = error_norm([0.003, 0.01, 0.3, float("nan")])
    assert isinstance(norm, LogNorm) and (norm.vmin, norm.vmax) == pytest.approx((0.003, 0.3))
    assert error_norm([0.0, 0.02]).vmin == ERROR_FLOOR_M  # an exact pose: the floor
    one = error_norm([0.005])  # one error: a decade around it
    assert one.vmax / one.vmin == pytest.approx(MIN_ERROR_SPAN) and one.vmin < 0.005 < one.vmax
    assert error_norm([1e-6, 1e-6]).vmin == ERROR_FLOOR_M  # not below the floor
    assert (error_norm([]).vmin, error_norm([]).vmax) == (1e-3, 1.0)
    fixed = error_norm([0.003, 0.01], max_error_m=1.0)  # the override
    assert (fixed.vmin, fixed.vmax) == pytest.approx((0.003, 1.0))
    with pytest.raises(InputError, match="max_error_m"):
        error_norm([0.1], max_error_m=0.0)
    assert [format_metres(v) for v in (0.002, 0.05, 0.2, 2.0)] == ["2 mm", "5 cm", "0.2 m", "2 m"]


def test_a_3mm_and_a_30cm_error_get_clearly_different_colours(axes) -> None:
    """The complaint: with a fixed 0-1 m scale, mm errors and a 0.28 m wrong success looked alike."""
    errors = [0.003, 0.004, 0.002, 0.3, 0.005]
    results = [_result(c, e) for c, e in zip(_ring(5), errors)]
    sc = plot_localization(axes, _ring(8, 1.5), results)
    axes.figure.canvas.draw()  # the colours as drawn
    rgb = sc.get_facecolors()[:, :3]
    assert len(rgb) == 5
    # RGB distances; the old linear 0-1 m scale gave 0.43 and 0.008
    assert np.linalg.norm(rgb[0] - rgb[3]) > 0.8  # 3 mm vs 0.3 m: far apart
    assert np.linalg.norm(rgb[2] - rgb[4]) > 0.2  # 2 mm vs 5 mm: still apart
    assert isinstance(sc.norm, LogNorm) and sc.norm.vmax == pytest.approx(0.3)
    old = plot_localization(axes, _ring(8, 1.5), results, max_error_m=1.0)  # an explicit scale still works
    assert old.norm.vmax == 1.0


def test_segments_join_each_usable_estimate_to_its_truth(axes) -> None:
    ring = _ring(4)
    results = [
        _result(ring[0], 0.1, estimate_offset=(0.1, 0, 0)),
        _result(ring[1], 0.2, estimate_offset=(0, 0, 0.2)),
        _result(ring[2], float("nan"), success=False, status="lost", estimate_offset=(0.5, 0, 0)),  # unusable
        _result(ring[3], float("nan"), success=False, status="too_few_matches"),
    ]
    plot_localization(axes, ring, results)
    (lines,) = [c for c in axes.collections if isinstance(c, LineCollection)]
    segments = sorted((tuple(np.round(s[0], 6)), tuple(np.round(s[1], 6))) for s in lines.get_segments())
    expected = sorted(
        [
            ((ring[0, 0] + 0.1, ring[0, 2]), (ring[0, 0], ring[0, 2])),
            ((ring[1, 0], ring[1, 2] + 0.2), (ring[1, 0], ring[1, 2])),
        ]
    )
    np.testing.assert_allclose(np.array(segments), np.array(expected), atol=1e-9)
    assert "estimate → ground truth" in [t.get_text() for t in axes.get_legend().get_texts()]


def test_localized_predicted_and_lost_frames_are_drawn_apart(axes) -> None:
    ring = _ring(6)
    statuses = ["localized", "predicted", "predicted", "lost", "localized", "dropped"]
    results = [
        _result(
            c,
            0.01 * (k + 1) if s in ("localized", "predicted") else float("nan"),
            success=s in ("localized", "predicted"),
            status=s,
        )
        for k, (c, s) in enumerate(zip(ring, statuses))
    ]
    plot_localization(axes, ring, results)
    by_label = dict(zip(*reversed(axes.get_legend_handles_labels())))
    localized = by_label["localized (2), colour = error"]
    predicted = by_label["predicted (2), colour = error"]
    failed = by_label["no usable pose: 1 lost, 1 dropped"]  # counted by status, in the order met
    assert (
        len(localized.get_offsets()) == 2
        and len(predicted.get_offsets()) == 2
        and len(failed.get_offsets()) == 2
    )
    paths = [a.get_paths()[0].vertices for a in (localized, predicted, failed)]
    assert all(len(a) != len(b) or not np.allclose(a, b) for i, a in enumerate(paths) for b in paths[i + 1 :])
    np.testing.assert_allclose(failed.get_offsets(), ring[[3, 5]][:, [0, 2]])


def test_no_legend_entry_for_what_is_not_there(axes) -> None:
    results = [_result((1.0, 0.0, 2.0), float("nan"), success=False, status="too_few_matches")]
    plot_localization(axes, np.zeros((0, 3)), results)
    labels = axes.get_legend_handles_labels()[1]
    assert labels == ["no usable pose: 1 too_few_matches"]  # no map, no line of one point, nothing localized
    assert not any("localized" in t or "predicted" in t or "estimate" in t for t in labels)


def test_segments_hidden_under_their_markers_get_no_legend_entry(axes) -> None:
    results = [_result(c, 0.001, estimate_offset=(0.001, 0, 0)) for c in _ring(6)]  # 1 mm on a 4 m ring
    plot_localization(axes, _ring(6, 1.5), results)
    (lines,) = [c for c in axes.collections if isinstance(c, LineCollection)]
    assert len(lines.get_segments()) == 6
    assert not any("estimate" in t for t in axes.get_legend_handles_labels()[1])


def test_the_error_over_time_panel(axes) -> None:
    ring = _ring(5)
    results = [
        _result(c, e, success=ok, status="localized" if ok else "lost", timestamp=100.0 + 0.5 * k)
        for k, (c, e, ok) in enumerate(
            zip(ring, [0.002, 0.02, float("nan"), 0.2, 0.004], [True, True, False, True, True])
        )
    ]
    sc = plot_error_over_time(axes, results)
    assert axes.get_yscale() == "log" and "time" in axes.get_xlabel()
    np.testing.assert_allclose(sc.get_offsets(), [[0.0, 0.002], [0.5, 0.02], [1.5, 0.2], [2.0, 0.004]])
    fail = [c for c in axes.collections if c is not sc and len(c.get_offsets()) == 1]
    assert len(fail) == 1 and fail[0].get_offsets()[0, 0] == pytest.approx(
        1.0
    )  # the lost frame, on the time axis
    no_stamps = [SimpleNamespace(**{**vars(r), "timestamp": None}) for r in results]
    t, label = result_times(no_stamps)
    assert t.tolist() == [0, 1, 2, 3, 4] and "index" in label


def test_the_saved_figure_has_the_top_view_the_time_panel_and_a_log_colour_bar(tmp_path, monkeypatch) -> None:
    from planarloc.viz import trajectory

    figures = []
    monkeypatch.setattr(plt, "close", lambda fig: figures.append(fig))
    ring = _ring(6)
    results = [
        _result(c, e, estimate_offset=(e, 0, 0), timestamp=float(k))
        for k, (c, e) in enumerate(zip(ring, [0.003, 0.004, 0.3, 0.002, 0.01, 0.005]))
    ]
    trajectory.save_localization_plot(tmp_path / "p.png", _ring(8, 1.5), results, "title")
    (fig,) = figures
    top, time_panel, bar = fig.axes
    assert top.get_title() == "title" and top.get_aspect() == 1.0
    assert time_panel.get_yscale() == "log" and "time" in time_panel.get_xlabel()
    assert bar.get_yscale() == "log" and "log scale" in bar.get_ylabel()
    assert (tmp_path / "p.png").stat().st_size > 1000
    monkeypatch.undo()
    plt.close(fig)
