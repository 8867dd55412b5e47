"""The map build the commands share (`map build`, `evaluate`, `demo`): :func:`build_map` with the
console's notes, the images it leaves out collected, then the map's std calibration when the build
changed the map (:func:`planarloc.localize.held_out.calibrate_map_std_when_due`), and the list of
the images it left out that ends those commands' output (exit code 3)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Unpack

from planarloc.cli.console import note, notify
from planarloc.cli.exit_codes import EXIT_PARTIAL
from planarloc.cli.warmup_command import compile_ahead
from planarloc.compile import steps_for
from planarloc.features.extract import FeatureConfig
from planarloc.localize.held_out import Progress, calibrate_map_std_when_due
from planarloc.map.builder import BuildRun, build_map
from planarloc.map.posed_image import PosedImage


class BuildOptions(BuildRun, total=False):
    """How :func:`build_calibrated_map` builds: keyword arguments of :func:`build_map`, all optional
    (its defaults where not given)."""

    #: the layout of a new map (:data:`planarloc.map.codec.STORAGE_LAYOUTS`)
    storage: str
    #: append images whose world frame looks unrelated to the map's
    allow_unrelated_frames: bool


def build_calibrated_map(
    images: Sequence[PosedImage],
    path: Path,
    features: FeatureConfig,
    num_words: int,
    progress: Progress,
    **build: Unpack[BuildOptions],
) -> list[tuple[str, str]]:
    """Build (or resume) the map at ``path`` and measure its std calibration when due; returns the
    images left out of the map, ``(name, reason)``, each also said on the console. ``build``: how
    (:class:`BuildOptions`, e.g. ``mapper``, ``storage``)."""
    left_out: list[tuple[str, str]] = []

    def skipped(image: PosedImage, reason: str) -> None:
        left_out.append((image.name, reason))
        note(f"image {image.name} left out of the map: {reason}")

    build_map(
        images,
        path,
        features,
        num_words=num_words,
        progress=progress,
        notify=notify,
        skipped=skipped,
        **build,
    )
    # The held-out images are localized: their kernels compile on every core first, as a query's do.
    calibrate_map_std_when_due(
        path,
        progress=progress,
        before_localizing=lambda config: compile_ahead(steps_for([config]), progress=progress),
    )
    return left_out


def left_out_exit(code: int, left_out: list[tuple[str, str]], total: int, what: str = "images") -> int:
    """The exit code ``code``, at least 3 ("partly done") when images were left out of the map
    (``left_out`` of the ``total`` ``what`` given to :func:`build_calibrated_map`), whose list it
    says on the console."""
    if not left_out:
        return code
    note(
        f"{len(left_out)} of {total} {what} were left out of the map (fix or remove them, then re-run "
        "the same command to add them):"
    )
    for name, reason in left_out:
        note(f"  {name}: {reason}")
    return max(code, EXIT_PARTIAL)
