"""Plots of localization results (the paper's Fig. 8): trajectory coloured by error.

Top-down view on the ground plane: planarloc's world y-axis is gravity, so the plot shows
world x (right) against world z (up the page). Functions take a matplotlib ``ax`` so they compose.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def plot_localization(ax, map_centers: np.ndarray, results: Sequence, max_error_m: float = 1.0,
                      title: str | None = None):
    """Draw the map trajectory, the query ground truth coloured by error, failures marked.

    Args:
        ax: a matplotlib Axes.
        map_centers: (M, 3) map camera centres (world).
        results: :class:`planarloc.evaluation.queries.QueryResult` items.
        max_error_m: upper end of the colour scale (errors above are clipped).

    Returns:
        The scatter artist (for a colour bar).
    """
    map_centers = np.asarray(map_centers, dtype=float).reshape(-1, 3)
    gt = np.array([r.truth_center for r in results], dtype=float).reshape(-1, 3)
    ok = np.array([r.success for r in results], dtype=bool)
    err = np.array([r.translation_error_m for r in results], dtype=float)
    ax.plot(map_centers[:, 0], map_centers[:, 2], "-", color="0.6", lw=2, label="map")
    ax.plot(gt[:, 0], gt[:, 2], "-", color="tab:green", lw=1, alpha=0.6, label="query ground truth")
    sc = ax.scatter(gt[ok, 0], gt[ok, 2], c=np.clip(err[ok], 0, max_error_m), cmap="viridis", vmin=0,
                    vmax=max_error_m, s=25, zorder=3, label="localized (colour = error)")
    if (~ok).any():
        ax.scatter(gt[~ok, 0], gt[~ok, 2], marker="x", color="tab:red", s=40, zorder=4, label="failed")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("world x [m]")
    ax.set_ylabel("world z [m]")
    if title:
        ax.set_title(title)
    ax.legend(loc="best", fontsize="small")
    return sc


def save_localization_plot(path, map_centers: np.ndarray, results: Sequence, title: str | None = None,
                           max_error_m: float = 1.0) -> None:
    """Write :func:`plot_localization` to an image file (headless backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6))
    sc = plot_localization(ax, map_centers, results, max_error_m, title)
    fig.colorbar(sc, ax=ax, label="position error [m]")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
