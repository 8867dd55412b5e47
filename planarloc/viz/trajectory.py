"""Plots of localization results (the paper's Fig. 8): a top view of the trajectory coloured by
position error, and the error over time.

**Top view.** The view looks straight down along the map's gravity ``g_world``
(``GravityReport.g_world``, :mod:`planarloc.gravity.world`) onto the plane perpendicular to it,
so gravity points into the page and the picture is a map, not its mirror image:

- page x (to the right) is the world axis most perpendicular to gravity (x first on a tie),
  levelled into that plane;
- page y (up the page) is ``up × x`` with ``up = −g_world``: horizontal, 90° to the left of
  page x.

The axes are labelled with the world axis they are, e.g. ``world x [m]``; ``−world z`` when it
is the negative axis, ``≈ world z`` when the map's gravity is tilted by more than 0.5° from the
world axis (then the plane is levelled, the axis is the nearest one). The numbers are world
coordinates in metres. For the usual worlds:

=================================================  ===============  =========  =========
world                                              gravity (down)   page x     page y
=================================================  ===============  =========  =========
y down (KITTI, planarloc's generated/demo worlds)  +y               world x    world z
z up (OpenLORIS, ROS REP 103)                      −z               world x    world y
=================================================  ===============  =========  =========

Nothing here says east or north: a map frame is only that if its data declares it.

**Markers.** Filled circle: a pose from an absolute fix (a single query's ``success``, a
stream's ``localized`` frame). Triangle with a dark edge: a stream's ``predicted`` frame (a pose
carried by the motion model). Red ×: no usable pose (a failed query; a stream's ``lost``,
``dropped`` or ``error`` frame). Circles and triangles are drawn at the ground-truth position,
coloured by position error on a logarithmic scale that spans the plotted errors
(:func:`error_norm`), so a 3 mm and a 0.3 m error differ at a glance. A thin dark line joins
each usable estimate to its ground truth (hidden under the marker when the error is small; it
gets a legend entry when one is longer than 0.5% of the view).

**Error over time** (:func:`plot_error_over_time`, the lower panel of
:func:`save_localization_plot`): position error on a log axis against the time since the first
result (its ``timestamp``) or, without timestamps, the result's index; results without a usable
pose are red × on the time axis; the dashed line is the paper's first success threshold.

Functions take a matplotlib ``ax`` so they compose. Results are read by attribute, the optional
ones with a default: ``truth_center``, ``success``, ``translation_error_m``, and
``estimate_center``, ``status``, ``timestamp`` if present
(:class:`planarloc.evaluation.queries.QueryResult`, a stream's
:class:`planarloc.evaluation.sequence.FrameResult`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TypedDict, Unpack

import numpy as np

from planarloc.evaluation.queries import THRESHOLDS
from planarloc.geometry.validation import InputError, check_positive

_AXES = ("x", "y", "z")
#: lower end of the colour scale in metres (0.1 mm); smaller errors, e.g. an exact pose, get its colour
ERROR_FLOOR_M = 1e-4
#: the colour scale spans at least this factor (one decade), so equal errors are not stretched over it
MIN_ERROR_SPAN = 10.0
CMAP = "viridis"  # a NaN error (a usable pose without one) is drawn grey
LOCALIZED, PREDICTED, FAILED = "localized", "predicted", "failed"
_APPROX_DEG = 0.5  # an axis this far from a world axis is labelled "≈ world ..."
_FAIL_STYLE = {"marker": "x", "color": "tab:red", "linewidths": 1.5}
_PREDICTED_STYLE = {"marker": "^", "edgecolors": "0.15", "linewidths": 0.6}
_LOCALIZED_STYLE = {"marker": "o", "edgecolors": "none"}
_SEGMENT_COLOR = "0.15"
#: the default ``g_world`` (down): +y, as in KITTI and planarloc's generated worlds
Y_DOWN = (0.0, 1.0, 0.0)


def gravity_plane_basis(g_world: object) -> tuple[np.ndarray, np.ndarray, str]:
    """``(e_x, e_y, label)``: orthonormal (3,) directions spanning the plane perpendicular to the
    gravity direction ``g_world`` (pointing down, any non-zero length), seen from above (module
    docstring), and the name of the world axis ``e_x`` was taken from.

    Example:
        >>> ex, ey, name = gravity_plane_basis([0, 1, 0])      # world y points down
        >>> ex.tolist(), ey.tolist(), name
        ([1.0, 0.0, 0.0], [0.0, 0.0, 1.0], 'x')
    """
    g = np.asarray(g_world, dtype=float).reshape(-1)
    n = float(np.linalg.norm(g)) if g.shape == (3,) else 0.0
    if not (np.isfinite(n) and n > 1e-9):
        raise InputError(
            f"g_world: expected a non-zero (3,) gravity direction, got {np.asarray(g_world).tolist()}"
        )
    g = g / n
    k = int(np.argmin(np.round(np.abs(g), 9)))  # the least aligned world axis (the first of equals)
    a = np.eye(3)[k]
    ex = a - (a @ g) * g
    ex /= np.linalg.norm(ex)
    ey = np.cross(-g, ex)
    return ex, ey, _AXES[k]


def axis_labels(g_world: object) -> tuple[str, str]:
    """``(x label, y label)`` of the top view of ``g_world``: the world axis each page axis is
    (module docstring), e.g. ``("world x [m]", "world z [m]")`` for a y-down world."""
    ex, ey, _ = gravity_plane_basis(g_world)

    def name(e: np.ndarray) -> str:
        k = int(np.argmax(np.abs(e)))
        off = math.degrees(math.acos(min(1.0, abs(float(e[k])))))
        sign = "−" if e[k] < 0 else ""
        return f"{'≈ ' if off > _APPROX_DEG else ''}{sign}world {_AXES[k]} [m]"

    return name(ex), name(ey)


def result_kind(result: object) -> str:
    """:data:`LOCALIZED` (a usable pose from a fix: ``success``, a stream's ``localized``),
    :data:`PREDICTED` (a stream's usable ``predicted`` pose) or :data:`FAILED` (no usable pose)."""
    if not bool(getattr(result, "success", False)):
        return FAILED
    return PREDICTED if getattr(result, "status", "") == PREDICTED else LOCALIZED


def error_norm(errors: object, max_error_m: float | None = None):
    """The logarithmic colour scale (a matplotlib ``LogNorm``) of position errors ``errors`` (m).

    It spans the finite errors, from ``max(smallest, ERROR_FLOOR_M)`` to the largest. A span of
    less than ``MIN_ERROR_SPAN`` (e.g. one result, or all errors equal) is widened to it around
    their geometric mean, not below the floor; without finite errors it is 1 mm to 1 m.
    ``max_error_m`` fixes the upper end instead (larger errors get its colour).
    """
    from matplotlib.colors import LogNorm

    check_positive("max_error_m", max_error_m, allow_none=True)
    e = np.asarray(errors, dtype=float).reshape(-1)
    e = e[np.isfinite(e)]
    lo, hi = (
        (max(float(e.min()), ERROR_FLOOR_M), max(float(e.max()), ERROR_FLOOR_M)) if e.size else (1e-3, 1.0)
    )
    if max_error_m is not None:
        hi = float(max_error_m)
        lo = min(lo, hi / MIN_ERROR_SPAN)
    elif hi < lo * MIN_ERROR_SPAN:
        mid = math.sqrt(lo * hi)
        lo = max(mid / math.sqrt(MIN_ERROR_SPAN), ERROR_FLOOR_M)
        hi = lo * MIN_ERROR_SPAN
    return LogNorm(vmin=lo, vmax=hi)


def format_metres(value: float, _pos: object = None) -> str:
    """A tick label in the unit that reads best: ``3 mm``, ``2 cm``, ``0.5 m``."""
    if not (np.isfinite(value) and value > 0):
        return ""
    if value < 0.01 - 1e-12:
        return f"{value * 1000:.3g} mm"
    if value < 0.1 - 1e-12:
        return f"{value * 100:.3g} cm"
    return f"{value:.3g} m"


def log_metre_axis(axis) -> None:
    """Ticks of a log-scaled metre axis (a matplotlib Axis) at 1, 2, 5 × 10^k, in mm/cm/m."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    axis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(format_metres))
    axis.set_minor_formatter(NullFormatter())


def _cmap():
    import matplotlib

    return matplotlib.colormaps[CMAP].with_extremes(bad="0.5")


def _errors(results: Sequence) -> np.ndarray:
    return np.array([getattr(r, "translation_error_m", float("nan")) for r in results], dtype=float).reshape(
        -1
    )


def _kinds_and_errors(results: Sequence, max_error_m: float | None = None, norm=None):
    """The results' kinds (:func:`result_kind`, an object array), their position errors (NaN
    without one) and the colour scale: ``norm`` if given, else :func:`error_norm` of the errors
    of the results that are not failures."""
    kinds = np.array([result_kind(r) for r in results], dtype=object)
    err = _errors(results)
    return kinds, err, error_norm(err[kinds != FAILED], max_error_m) if norm is None else norm


def _estimates(results: Sequence) -> np.ndarray:
    """(N, 3) estimated centres, NaN where a result has none."""
    out = np.full((len(results), 3), np.nan)
    for i, r in enumerate(results):
        c = getattr(r, "estimate_center", None)
        if c is not None:
            out[i] = np.asarray(c, dtype=float).reshape(3)
    return out


def _failure_label(results: Sequence, failed: np.ndarray) -> str:
    counts: dict[str, int] = {}
    for r, f in zip(results, failed):
        if f:
            s = getattr(r, "status", FAILED)
            s = str(getattr(s, "value", s))
            counts[s] = counts.get(s, 0) + 1
    if len(counts) > 3:
        return f"no usable pose ({int(failed.sum())})"
    return "no usable pose: " + ", ".join(
        f"{n} {s}" for s, n in sorted(counts.items(), key=lambda kv: -kv[1])
    )


def _draw_segments(ax, map_xy: np.ndarray, gt: np.ndarray, est: np.ndarray, usable: np.ndarray) -> None:
    """Estimate → truth lines of the usable results with an estimate ((N, 2) top-view points),
    and a dot at each estimate."""
    from matplotlib.collections import LineCollection

    seg = usable & np.isfinite(est).all(axis=1)
    if seg.any():
        # a legend entry only when some segment shows beside its marker (longer than 0.5% of the view)
        drawn = np.concatenate([map_xy, gt, est[seg]])
        shows = np.linalg.norm(est[seg] - gt[seg], axis=1).max() > 0.005 * float(np.ptp(drawn, axis=0).max())
        ax.add_collection(
            LineCollection(
                list(np.stack([est[seg], gt[seg]], axis=1)),
                colors=_SEGMENT_COLOR,
                linewidths=0.8,
                alpha=0.8,
                zorder=2.5,
                label="estimate → ground truth" if shows else None,
            )
        )
        ax.scatter(est[seg, 0], est[seg, 1], s=5, color=_SEGMENT_COLOR, zorder=2.6)


def _error_scatter(
    ax, x: np.ndarray, y: np.ndarray, error: np.ndarray, norm, size: float, label: str | None, style: dict
):
    """Markers at ``(x, y)`` (N,) each coloured by its ``error`` (N,) on the shared colour scale."""
    return ax.scatter(
        x,
        y,
        c=error,
        cmap=_cmap(),
        norm=norm,
        s=size,
        zorder=3,
        plotnonfinite=True,
        label=label,
        **style,
    )


def plot_localization(
    ax,
    map_centers: np.ndarray,
    results: Sequence,
    max_error_m: float | None = None,
    title: str | None = None,
    g_world: object = Y_DOWN,
    norm=None,
):
    """Draw the top view (module docstring): the map trajectory, the ground truth, a marker per
    result at its true position (coloured by error, failures marked) and estimate → truth lines.

    Args:
        ax: a matplotlib Axes.
        map_centers: (M, 3) map camera centres (world, metres).
        results: items with ``truth_center`` (3,), ``success`` and ``translation_error_m`` (m),
            and optionally ``estimate_center`` (3,) or None, and ``status``
            (:class:`planarloc.evaluation.queries.QueryResult`, or a stream's
            :class:`planarloc.evaluation.sequence.FrameResult`).
        max_error_m: upper end of the colour scale (errors above get its colour); None: the
            largest usable error (:func:`error_norm`).
        title: the axes title.
        g_world: (3,) the map's gravity direction (down) in its world frame.
        norm: a matplotlib colour norm to use instead (e.g. shared with another panel).

    Returns:
        The scatter artist of the localized results (for a colour bar; it carries the norm even
        when it has no points).
    """

    ex, ey, _ = gravity_plane_basis(g_world)
    P = np.stack([ex, ey], axis=1)
    map_xy = np.asarray(map_centers, dtype=float).reshape(-1, 3) @ P
    gt = np.array([r.truth_center for r in results], dtype=float).reshape(-1, 3) @ P
    est = _estimates(results) @ P
    kinds, err, norm = _kinds_and_errors(results, max_error_m, norm)
    c = np.clip(err, norm.vmin, norm.vmax)

    if len(map_xy):  # one map image: a square, as a line of one point is not drawn
        ax.plot(
            map_xy[:, 0],
            map_xy[:, 1],
            "-" if len(map_xy) > 1 else "s",
            color="0.6",
            lw=2,
            label="map cameras",
        )
    if len(gt) > 1:  # one result: its marker is all there is
        ax.plot(gt[:, 0], gt[:, 1], "-", color="tab:green", lw=1, alpha=0.6, label="ground truth")
    _draw_segments(ax, map_xy, gt, est, kinds != FAILED)
    loc, pred, fail = kinds == LOCALIZED, kinds == PREDICTED, kinds == FAILED
    loc_label = f"localized ({int(loc.sum())}), colour = error" if loc.any() else None
    sc = _error_scatter(ax, gt[loc, 0], gt[loc, 1], c[loc], norm, 30, loc_label, _LOCALIZED_STYLE)
    if pred.any():
        _error_scatter(
            ax,
            gt[pred, 0],
            gt[pred, 1],
            c[pred],
            norm,
            36,
            f"predicted ({int(pred.sum())}), colour = error",
            _PREDICTED_STYLE,
        )
    if fail.any():
        ax.scatter(
            gt[fail, 0], gt[fail, 1], s=40, zorder=4, label=_failure_label(results, fail), **_FAIL_STYLE
        )
    ax.set_aspect("equal", adjustable="datalim")
    xlabel, ylabel = axis_labels(g_world)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize="small")
    return sc


_TIME_LABEL, _INDEX_LABEL = "time since the first image [s]", "image index (no timestamps)"


def _stamp(result: object) -> float:
    """The result's ``timestamp`` (else a stream frame's ``stamp``) in seconds, NaN without one."""
    value = getattr(result, "timestamp", None)
    value = getattr(result, "stamp", None) if value is None else value
    try:
        return float(value)  # type: ignore[arg-type]  # any object: float() decides, TypeError handled
    except (TypeError, ValueError):
        return float("nan")


def result_times(results: Sequence) -> tuple[np.ndarray, str]:
    """``(t, label)``: seconds since the earliest result when every result has a finite
    ``timestamp`` (a stream frame: else its ``stamp``) and they differ, else the results'
    indices."""
    t = np.array([_stamp(r) for r in results], dtype=float)
    if len(t) and np.isfinite(t).all() and np.ptp(t) > 0:
        return t - t.min(), _TIME_LABEL
    return np.arange(len(results), dtype=float), _INDEX_LABEL


def plot_error_over_time(ax, results: Sequence, norm=None, max_error_m: float | None = None):
    """Position error against time (module docstring): log y axis, markers as in the top view,
    results without a usable pose as red × on the time axis, the paper's first threshold dashed.

    Args:
        ax: a matplotlib Axes.
        results: as for :func:`plot_localization`; ``timestamp`` (s) is used when every result
            has one.
        norm: the colour norm (e.g. the top view's); None: :func:`error_norm`.
        max_error_m: as for :func:`plot_localization`, when ``norm`` is None.

    Returns:
        The scatter artist of the localized results.
    """
    from matplotlib.ticker import MaxNLocator

    t, t_label = result_times(results)
    kinds, err, norm = _kinds_and_errors(results, max_error_m, norm)
    shown = np.maximum(err, ERROR_FLOOR_M)
    usable = (kinds != FAILED) & np.isfinite(err)
    order = np.argsort(t, kind="stable")  # a line through the usable errors, broken where a pose is missing
    ax.plot(t[order], np.where(usable, shown, np.nan)[order], "-", color="0.75", lw=0.8, zorder=1)
    loc, pred, fail = usable & (kinds == LOCALIZED), usable & (kinds == PREDICTED), kinds == FAILED
    c = np.clip(err, norm.vmin, norm.vmax)
    sc = _error_scatter(ax, t[loc], shown[loc], c[loc], norm, 18, None, _LOCALIZED_STYLE)
    if pred.any():
        _error_scatter(ax, t[pred], shown[pred], c[pred], norm, 24, None, _PREDICTED_STYLE)
    threshold = THRESHOLDS[0][0]
    ax.axhline(threshold, color="tab:red", lw=0.8, ls="--", alpha=0.7, zorder=0)
    ax.set_yscale("log")
    lo = min(norm.vmin, float(shown[usable].min()) if usable.any() else norm.vmin)
    hi = max(norm.vmax, threshold, float(shown[usable].max()) if usable.any() else norm.vmax)
    ax.set_ylim(lo / 1.6, hi * 1.6)
    ax.text(
        1.0,
        threshold,
        f" {format_metres(threshold)}\n threshold",
        transform=ax.get_yaxis_transform(),
        color="tab:red",
        fontsize="x-small",
        va="center",
        ha="left",
        clip_on=False,
    )
    if fail.any():  # on the time axis: y in axes coordinates
        ax.scatter(
            t[fail],
            np.zeros(int(fail.sum())),
            s=30,
            transform=ax.get_xaxis_transform(),
            clip_on=False,
            zorder=4,
            **_FAIL_STYLE,
        )
    log_metre_axis(ax.yaxis)
    ax.set_xlabel(t_label)
    ax.set_ylabel("position error")
    ax.grid(True, which="major", axis="y", color="0.9", lw=0.6)
    if len(t):
        span = float(np.ptp(t))
        pad = max(0.02 * span, 0.5) if t_label == _INDEX_LABEL else 0.02 * span
        ax.set_xlim(float(t.min()) - pad, float(t.max()) + pad)
    if t_label == _INDEX_LABEL:
        ax.xaxis.set_major_locator(MaxNLocator(integer=True, min_n_ticks=1))
    return sc


_TOP_VIEW_WIDTH_IN, _TIME_PANEL_IN = 5.4, 2.0  # inches: the top view's width, the time panel's height


def _top_view_height(map_centers: np.ndarray, results: Sequence, g_world: object) -> float:
    """Height in inches of the top view's panel that fits the drawn points at equal aspect."""
    ex, ey, _ = gravity_plane_basis(g_world)
    pts = np.concatenate(
        [
            np.asarray(map_centers, dtype=float).reshape(-1, 3),
            np.array([r.truth_center for r in results], dtype=float).reshape(-1, 3),
        ]
    )
    pts = pts[np.isfinite(pts).all(axis=1)] @ np.stack([ex, ey], axis=1)
    dx, dy = np.ptp(pts, axis=0) if len(pts) else (1.0, 1.0)
    aspect = float(np.clip((dy + 1e-9) / (dx + 1e-9), 0.4, 1.5))
    return _TOP_VIEW_WIDTH_IN * aspect + 0.9  # + title and axis label


class TopViewOptions(TypedDict, total=False):
    """The top view's options that :func:`save_localization_plot` takes as keywords and passes on
    to :func:`plot_localization` (the same meaning and defaults)."""

    #: upper end of the colour scale; None: the largest usable error
    max_error_m: float | None
    #: (3,) the map's gravity direction (down) in its world frame
    g_world: object


def save_localization_plot(
    path, map_centers: np.ndarray, results: Sequence, title: str | None = None, **view: Unpack[TopViewOptions]
) -> None:
    """Write the top view (:func:`plot_localization`) above the error over time
    (:func:`plot_error_over_time`), one colour scale for both, to an image file (headless backend).

    ``view``: ``max_error_m`` (upper end of the colour scale; None: the largest usable error) and
    ``g_world`` (:class:`TopViewOptions`).
    """
    unknown = sorted(set(view) - set(TopViewOptions.__annotations__))
    if unknown:
        raise TypeError(f"save_localization_plot() got unexpected keyword argument(s): {', '.join(unknown)}")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds, err, norm = _kinds_and_errors(results, view.get("max_error_m"))
    top = _top_view_height(map_centers, results, view.get("g_world", Y_DOWN))
    fig = plt.figure(figsize=(7.5, top + _TIME_PANEL_IN + 0.9), layout="constrained")
    grid = fig.add_gridspec(2, 1, height_ratios=(top, _TIME_PANEL_IN))
    ax, ax_t = fig.add_subplot(grid[0]), fig.add_subplot(grid[1])
    sc = plot_localization(ax, map_centers, results, title=title, norm=norm, **view)
    plot_error_over_time(ax_t, results, norm=norm)
    usable = err[(kinds != FAILED) & np.isfinite(err)]
    below, above = bool((usable < norm.vmin).any()), bool((usable > norm.vmax).any())
    extend = {(False, False): "neither", (True, False): "min", (False, True): "max", (True, True): "both"}[
        below, above
    ]
    if usable.size:  # a colour bar without coloured points would only be noise
        bar = fig.colorbar(sc, ax=[ax, ax_t], label="position error (log scale)", extend=extend, shrink=0.9)
        log_metre_axis(bar.ax.yaxis)
    fig.savefig(path, dpi=120)
    plt.close(fig)
