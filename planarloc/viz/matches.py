"""Match plots (the paper's Fig. 9): a query beside each of its reference images, with the
matches the estimator saw, inliers and outliers in two colours.

Every match is a small dot at both ends; lines are drawn for at most :data:`MAX_LINES` of them per
pair (:func:`lines_to_draw`: a seeded random subsample, inliers preferred), the outliers first,
thin and transparent, the inliers last, on top. Each row's title says how many lines of how many
matches are drawn.

Functions take a matplotlib ``ax`` so they compose; :func:`save_match_plot` writes one figure
per query (one row per reference). :func:`query_pairs` recovers the matches behind an
estimate (matching is deterministic, so re-matching the query's features to the estimate's
references yields the pairs whose inlier masks the estimate holds).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from planarloc.features.extract import Features
from planarloc.features.images import read_bgr
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose, pose_errors
from planarloc.localize.localizer import Localizer
from planarloc.robust.pair_matches import PairMatches
from planarloc.robust.result import PoseEstimate

INLIER_COLOR = "#1a9850"  # green
OUTLIER_COLOR = "#d73027"  # red
#: lines drawn per pair, at most: more hide the images and each other (the dots show every match)
MAX_LINES = 100
#: share of MAX_LINES kept for outliers when there are more inliers than fit
OUTLIER_SHARE = 0.25


def query_pairs(
    localizer: Localizer, features: Features, camera: Camera, estimate: PoseEstimate
) -> tuple[list[PairMatches], list[np.ndarray | None]]:
    """The matched pairs behind ``estimate`` and their inlier masks (None for a pair the
    estimator did not score, e.g. after ``too_few_matches``).

    Raises:
        ValueError: the re-matched references differ from the estimate's (the map changed).
    """
    pairs, names = localizer.pairs_for(
        features, estimate.references, camera, keypoint_budget=estimate.keypoint_budget
    )
    if names != list(estimate.references):
        raise ValueError("the matches of this estimate cannot be recovered (did the map change?)")
    inliers: list[np.ndarray | None] = []
    for k, p in enumerate(pairs):
        m = estimate.inliers[k] if k < len(estimate.inliers) else None
        inliers.append(np.asarray(m, bool) if m is not None and len(m) == len(p.query_points) else None)
    return pairs, inliers


def _rgb(path: Path | str) -> np.ndarray:
    return cv2.cvtColor(read_bgr(path), cv2.COLOR_BGR2RGB)  # pixels as stored, as the keypoints


def lines_to_draw(
    inliers: np.ndarray, max_lines: int = MAX_LINES, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """``(outlier indices, inlier indices)``, sorted, of the matches whose lines are drawn.

    At most ``max_lines`` in all, chosen at random with ``numpy.random.default_rng(seed)``,
    inliers preferred: outliers get ``OUTLIER_SHARE`` of the lines when there are more inliers
    than fit, and whatever the inliers leave otherwise.

    Args:
        inliers: (N,) bool, True for an inlier.
        max_lines: the most lines to draw (>= 0).
        seed: seed of the subsample (the same plot each run).

    Example:
        >>> out, inl = lines_to_draw(np.arange(500) < 400, max_lines=100)
        >>> len(out), len(inl)
        (25, 75)
    """
    inl = np.asarray(inliers, dtype=bool).reshape(-1)
    in_idx, out_idx = np.flatnonzero(inl), np.flatnonzero(~inl)
    max_lines = max(int(max_lines), 0)
    n_in = min(len(in_idx), max_lines - min(len(out_idx), int(OUTLIER_SHARE * max_lines)))
    n_out = min(len(out_idx), max_lines - n_in)
    rng = np.random.default_rng(seed)

    def pick(idx: np.ndarray, n: int) -> np.ndarray:
        return idx if n >= len(idx) else np.sort(rng.choice(idx, n, replace=False))

    return pick(out_idx, n_out), pick(in_idx, n_in)


def plot_pair(
    ax,
    query_image: np.ndarray,
    ref_image: np.ndarray,
    pair: PairMatches,
    inliers: np.ndarray | None,
    ref_label: str = "",
    seed: int = 0,
    max_lines: int = MAX_LINES,
) -> None:
    """Query (left) and reference (right) side by side: a dot at both ends of every match and
    lines for a subsample of them (:func:`lines_to_draw`), inliers drawn last, on top.

    Args:
        ax: a matplotlib Axes.
        query_image, ref_image: (H, W, 3) RGB or (H, W) gray images.
        pair: the matches (query and reference pixel coordinates, N each).
        inliers: (N,) bool, or None when the estimator did not score them (drawn red).
        ref_label: text under the reference.
        seed: seed of the line subsample.
        max_lines: the most match lines drawn.
    """
    from matplotlib.collections import LineCollection

    h = max(query_image.shape[0], ref_image.shape[0])

    def pad(img: np.ndarray) -> np.ndarray:
        img = img if img.ndim == 3 else np.repeat(img[:, :, None], 3, axis=2)
        return np.pad(img, ((0, h - img.shape[0]), (0, 0), (0, 0)), constant_values=255)

    ax.imshow(np.concatenate([pad(query_image), pad(ref_image)], axis=1))
    off = query_image.shape[1]
    q, r = pair.query_points, pair.ref_points
    inl = np.zeros(len(q), bool) if inliers is None else np.asarray(inliers, bool)
    out_idx, in_idx = lines_to_draw(inl, max_lines, seed)
    # unscored matches are all the pair has: drawn stronger than the outliers of a scored pair
    out_style = (0.6, 0.75) if inliers is None else (0.6, 0.55)  # (line width, alpha)
    for idx, mask, color, (width, alpha), z in (
        (out_idx, ~inl, OUTLIER_COLOR, out_style, 2),
        (in_idx, inl, INLIER_COLOR, (0.8, 0.9), 3),
    ):
        ends = np.concatenate([q[mask], r[mask] + [off, 0]])
        if len(ends):
            ax.scatter(ends[:, 0], ends[:, 1], s=2, color=color, zorder=z)
        if len(idx):
            segments = np.stack([q[idx], r[idx] + [off, 0]], axis=1)  # (n, 2 ends, xy)
            ax.add_collection(
                LineCollection(list(segments), colors=color, linewidths=width, alpha=alpha, zorder=z)
            )
    ax.set_axis_off()
    n_in, n_out = int(inl.sum()), int((~inl).sum())
    if inliers is None:
        counts = f"{len(q)} matches, not scored (red); lines for {len(out_idx)} of them"
    else:
        counts = (
            f"{n_in} inliers (green), {n_out} outliers (red); lines for {len(in_idx)} of {n_in} inliers, "
            f"{len(out_idx)} of {n_out} outliers"
        )
    ax.set_title(f"query | {ref_label}: {counts}", fontsize="small")


def estimate_caption(name: str, estimate: PoseEstimate, truth: Pose | None) -> str:
    """``name: status, inliers, position std, error vs. ground truth (if known)``."""
    parts = [f"{name}: {estimate.status}", f"{estimate.num_inliers} inliers"]
    if np.isfinite(estimate.position_std_m):
        parts.append(f"position std {estimate.position_std_m:.3f} m")
    if truth is None:
        parts.append("no ground truth")
    elif estimate.success and estimate.pose is not None:
        t_err, r_err = pose_errors(estimate.pose, truth)
        parts.append(f"error {t_err:.3f} m / {r_err:.2f}°")
    return ", ".join(parts)


def save_match_plot(
    path: Path | str,
    query_path: Path | str,
    ref_paths: Sequence[Path | str],
    pairs: Sequence[PairMatches],
    inliers: Sequence[np.ndarray | None],
    estimate: PoseEstimate,
    name: str,
    truth: Pose | None = None,
) -> Path:
    """Write one figure: a row per reference (query | reference with its matches), the
    estimate's status and, if ``truth`` (the query's ``cam_from_world``) is known, its error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    query = _rgb(query_path)
    rows = max(1, len(pairs))
    aspect = query.shape[0] / (2 * query.shape[1])
    fig, axes = plt.subplots(rows, 1, figsize=(10, 10 * aspect * rows + 0.6), squeeze=False)
    for k, ax in enumerate(axes[:, 0]):
        if k < len(pairs):
            plot_pair(
                ax, query, _rgb(ref_paths[k]), pairs[k], inliers[k], str(estimate.references[k]), seed=k
            )
        else:
            ax.imshow(query)
            ax.set_axis_off()
            ax.set_title("no reference image with enough matches", fontsize="small")
    fig.suptitle(estimate_caption(name, estimate, truth), fontsize="medium")
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.5 / fig.get_figheight()))
    fig.set_dpi(100)
    fig.canvas.draw()  # encode with OpenCV: several times faster than matplotlib's PNG writer
    canvas = fig.canvas
    if not isinstance(canvas, FigureCanvasAgg):  # matplotlib.use("Agg") above: never
        plt.close(fig)
        raise TypeError(f"expected matplotlib's Agg canvas, got {type(canvas).__name__}")
    rgba = np.asarray(canvas.buffer_rgba())
    plt.close(fig)
    if not cv2.imwrite(str(path), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise ValueError(f"{path}: cannot write the match plot")
    return path


def match_plot_name(query_name: str) -> str:
    """File name of a query's match plot: its name with '/' replaced, as PNG."""
    return query_name.replace("/", "__").rsplit(".", 1)[0] + ".png"


class MatchPlotter:
    """Writes :func:`save_match_plot` figures to ``out_dir`` for each estimate it is given
    (an ``on_estimate`` callback of :func:`planarloc.evaluation.queries.evaluate_configs`)."""

    def __init__(self, out_dir: Path | str) -> None:
        self.out_dir = Path(out_dir)
        self._paths: dict[int, dict[str, Path]] = {}
        self.written: list[Path] = []

    def _map_paths(self, localizer: Localizer) -> dict[str, Path]:
        key = id(localizer.db)
        if key not in self._paths:
            self._paths[key] = {p.name: Path(p.path) for p in localizer.map_images}
        return self._paths[key]

    def plot(
        self,
        localizer: Localizer,
        name: str,
        query_path: Path | str,
        camera: Camera,
        features: Features,
        estimate: PoseEstimate,
        truth: Pose | None = None,
    ) -> Path:
        """Plot one estimate; returns the written file."""
        pairs, inliers = query_pairs(localizer, features, camera, estimate)
        paths = self._map_paths(localizer)
        path = save_match_plot(
            self.out_dir / match_plot_name(name),
            query_path,
            [paths[n] for n in estimate.references],
            pairs,
            inliers,
            estimate,
            name,
            truth,
        )
        self.written.append(path)
        return path

    def __call__(self, localizer: Localizer, query, features: Features, estimate: PoseEstimate) -> None:
        self.plot(localizer, query.name, query.path, query.camera, features, estimate, query.cam_from_world)
