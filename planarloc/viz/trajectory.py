"""Plots of localization results (the paper's Fig. 8): trajectory coloured by error.

A top view in the map's **gravity plane**, the plane perpendicular to the map's gravity
(``GravityReport.g_world``, :mod:`planarloc.gravity.world`), seen from above: the page's x axis
is the world axis most perpendicular to gravity, projected into the plane (x first on a tie),
its y axis is ``up × x`` with ``up = −g_world``. For a world whose y axis is gravity (KITTI,
planarloc's generated worlds) that is world x against world z; for a z-up world (OpenLORIS)
world x against world y. Functions take a matplotlib ``ax`` so they compose.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from planarloc.geometry.validation import InputError

_AXES = ("x", "y", "z")


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
        raise InputError(f"g_world: expected a non-zero (3,) gravity direction, got {np.asarray(g_world).tolist()}")
    g = g / n
    k = int(np.argmin(np.round(np.abs(g), 9)))  # the least aligned world axis (the first of equals)
    a = np.eye(3)[k]
    ex = a - (a @ g) * g
    ex /= np.linalg.norm(ex)
    ey = np.cross(-g, ex)
    return ex, ey, _AXES[k]


def plot_localization(ax, map_centers: np.ndarray, results: Sequence, max_error_m: float = 1.0,
                      title: str | None = None, g_world: object = (0.0, 1.0, 0.0)):
    """Draw the map trajectory, the query ground truth coloured by error, failures marked, in
    the gravity plane of ``g_world`` (module docstring).

    Args:
        ax: a matplotlib Axes.
        map_centers: (M, 3) map camera centres (world).
        results: items with ``truth_center``, ``success`` and ``translation_error_m``
            (:class:`planarloc.evaluation.queries.QueryResult`, or a stream's
            :class:`planarloc.evaluation.sequence.FrameResult`).
        max_error_m: upper end of the colour scale (errors above are clipped).
        g_world: (3,) the map's gravity direction (down) in its world frame.

    Returns:
        The scatter artist (for a colour bar).
    """
    ex, ey, name = gravity_plane_basis(g_world)
    P = np.stack([ex, ey], axis=1)
    map_xy = np.asarray(map_centers, dtype=float).reshape(-1, 3) @ P
    gt = np.array([r.truth_center for r in results], dtype=float).reshape(-1, 3) @ P
    ok = np.array([r.success for r in results], dtype=bool)
    err = np.array([r.translation_error_m for r in results], dtype=float)
    ax.plot(map_xy[:, 0], map_xy[:, 1], "-", color="0.6", lw=2, label="map")
    ax.plot(gt[:, 0], gt[:, 1], "-", color="tab:green", lw=1, alpha=0.6, label="query ground truth")
    sc = ax.scatter(gt[ok, 0], gt[ok, 1], c=np.clip(err[ok], 0, max_error_m), cmap="viridis", vmin=0,
                    vmax=max_error_m, s=25, zorder=3, label="with a pose (colour = error)")
    if (~ok).any():
        ax.scatter(gt[~ok, 0], gt[~ok, 1], marker="x", color="tab:red", s=40, zorder=4, label="failed")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"gravity plane: along world {name} [m]")
    ax.set_ylabel(f"gravity plane: up × world {name} [m]")
    if title:
        ax.set_title(title)
    ax.legend(loc="best", fontsize="small")
    return sc


def save_localization_plot(path, map_centers: np.ndarray, results: Sequence, title: str | None = None,
                           max_error_m: float = 1.0, g_world: object = (0.0, 1.0, 0.0)) -> None:
    """Write :func:`plot_localization` to an image file (headless backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6))
    sc = plot_localization(ax, map_centers, results, max_error_m, title, g_world)
    fig.colorbar(sc, ax=ax, label="position error [m]")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
