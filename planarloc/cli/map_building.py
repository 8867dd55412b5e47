"""The map build the commands share (`map build`, `evaluate`, `demo`): :func:`build_map` with the
console's notes, the images it leaves out collected, then the map's std calibration when the build
changed the map (:func:`planarloc.localize.held_out.calibrate_map_std_when_due`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from planarloc.cli.console import note, notify
from planarloc.features.extract import FeatureConfig
from planarloc.localize.held_out import Progress, calibrate_map_std_when_due
from planarloc.map.builder import Mapper, build_map
from planarloc.map.codec import DEFAULT_STORAGE
from planarloc.map.posed_image import PosedImage


def build_calibrated_map(
    images: Sequence[PosedImage],
    path: Path,
    features: FeatureConfig,
    num_words: int,
    progress: Progress,
    *,
    mapper: Mapper | None = None,
    storage: str = DEFAULT_STORAGE,
    allow_unrelated_frames: bool = False,
) -> list[tuple[str, str]]:
    """Build (or resume) the map at ``path`` and measure its std calibration when due; returns the
    images left out of the map, ``(name, reason)``, each also said on the console."""
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
        storage=storage,
        allow_unrelated_frames=allow_unrelated_frames,
        mapper=mapper,
    )
    calibrate_map_std_when_due(path, progress=progress)
    return left_out
