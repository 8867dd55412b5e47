"""Tables and files that the evaluate / demo commands write."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from rich.table import Table

from planarloc.cli.console import info, note
from planarloc.cli.exit_codes import EXIT_OK, EXIT_PARTIAL
from planarloc.io import strict_json
from planarloc.io.output import atomic_output, write_text_atomic


def print_summary_table(summaries: Sequence[dict], title: str) -> None:
    """One row per (method, structure): success at the paper's thresholds, errors, failures, time."""
    if not summaries:
        return
    table = Table(title=title, min_width=100)
    table.add_column("method")
    table.add_column("structure")
    for key in summaries[0]["success"]:
        table.add_column(key, justify="right")
    for col in ("median t [m]", "median R [°]", "failed", "degenerate", "s/query"):
        table.add_column(col, justify="right")
    for s in summaries:
        mt, mr = s["median_translation_error_m"], s["median_rotation_error_deg"]
        table.add_row(
            s["method"],
            s["structure"],
            *[f"{v:.1f}%" for v in s["success"].values()],
            "-" if mt is None else f"{mt:.3f}",
            "-" if mr is None else f"{mr:.2f}",
            f"{s['failed_queries']}/{s['queries']}",
            str(s["status_counts"].get("degenerate_scale", 0)),
            f"{s['seconds_per_query']:.2f}",
        )
    info(table)


def write_json(path: Path | None, data: object) -> None:
    if path is None:
        return
    write_text_atomic(Path(path), strict_json.dumps(data, indent=1))
    info(f"wrote {path}")


def write_trajectory_plot(
    path: Path | None, map_images: Sequence, results: Sequence, title: str, g_world: object
) -> None:
    """The trajectory plot (``--plot``) in the map's gravity plane (:mod:`planarloc.viz.trajectory`)."""
    if path is None:
        return
    from planarloc.viz.trajectory import save_localization_plot

    centers = np.array([m.cam_from_world.center for m in map_images])
    with atomic_output(path) as tmp:
        save_localization_plot(tmp, centers, results, title, g_world=g_world)
    info(f"wrote {path}")


def partial_exit(results: Sequence, what: str) -> int:
    """3 (and a note) when some of the ``results`` could not be processed (status ``error``), else 0."""
    errors = [r for r in results if r.status == "error"]
    if errors:
        note(
            f"{len(errors)} of {len(results)} {what} could not be processed (e.g. {errors[0].reason}); they "
            "count as failed"
        )
        return EXIT_PARTIAL
    return EXIT_OK
