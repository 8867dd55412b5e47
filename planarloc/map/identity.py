"""Which images of a new build are already in a map: identity by content, not by name.

A map stores, per image, the SHA-256 of its source file and its pose. When a build is run
again on a map (resume, append, or a corrected dataset), every incoming image whose name is
already stored is compared with the stored one:

==========================  ==================  ==============================================
file content                pose / camera       action
==========================  ==================  ==============================================
same                        same                keep (resume); a moved file only updates the path
same                        different           **update** the pose (features stay valid)
different, same file path   any                 **replace**: the image changed, re-extract it
different, other file path  any                 **namespace**: another dataset's image with the
                                                same name is stored as ``<dataset>/<name>``
==========================  ==================  ==============================================

Maps written before content hashes were stored have no hash: an image at the same path then
counts as the same content. Each action is reported in one log line naming an example image.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from planarloc.geometry.validation import InputError
from planarloc.map.posed_image import PosedImage
from planarloc.map.store import MapDatabase

logger = logging.getLogger(__name__)

#: Poses closer than this (rotation matrix entries, translation in metres) are the same pose.
POSE_TOLERANCE = 1e-9


def file_sha256(path: Path) -> str:
    """SHA-256 (hex) of a file's bytes.

    Raises:
        InputError: the file is missing or unreadable (named in the message).
    """
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            while chunk := f.read(1 << 20):
                h.update(chunk)
    except OSError as exc:
        raise InputError(f"{path}: cannot read image ({exc.strerror or exc})") from None
    return h.hexdigest()


@dataclass
class MapUpdatePlan:
    """What a build does with its images; lists of the incoming (possibly renamed) records."""

    add: list[tuple[PosedImage, str]] = field(default_factory=list)  # new: extract and insert
    keep: list[str] = field(default_factory=list)  # identical: nothing to do
    update: list[tuple[PosedImage, str]] = field(default_factory=list)  # pose / path / camera params
    replace: list[tuple[PosedImage, str]] = field(default_factory=list)  # content changed: re-extract
    renamed: list[tuple[str, str]] = field(default_factory=list)  # (original name, stored name)

    @property
    def changes_map(self) -> bool:
        return bool(self.add or self.update or self.replace)

    def summary_lines(self, map_path: Path) -> list[str]:
        """One line per action taken (empty if the map only gets resumed)."""
        lines = []
        if self.update:
            lines.append(
                f"{map_path}: {len(self.update)} image(s) already in the map have a new pose, camera or "
                f"path (e.g. {self.update[0][0].name}); updated them, their features stay"
            )
        if self.replace:
            lines.append(
                f"{map_path}: {len(self.replace)} image file(s) changed since they were mapped "
                f"(e.g. {self.replace[0][0].name}); re-extracted their features"
            )
        if self.renamed:
            o, n = self.renamed[0]
            lines.append(
                f"{map_path}: {len(self.renamed)} image name(s) are already used by different images "
                f"of another dataset (e.g. {o}); stored these as {n} etc. to keep both"
            )
        return lines


def _same_pose(a: PosedImage, b: PosedImage) -> bool:
    pa, pb = a.cam_from_world, b.cam_from_world
    return bool(np.abs(pa.R - pb.R).max() <= POSE_TOLERANCE and np.abs(pa.t - pb.t).max() <= POSE_TOLERANCE)


def _same_record(stored: PosedImage, new: PosedImage) -> bool:
    return (
        _same_pose(stored, new)
        and stored.camera == new.camera
        and Path(stored.path) == Path(new.path)
        and stored.timestamp == new.timestamp
        and stored.depth_path == new.depth_path
        and stored.depth_scale == new.depth_scale
    )


def _dataset_prefix(image: PosedImage) -> str:
    """The dataset folder name of an image: its path minus its name (e.g. ``seq05``)."""
    path, name = str(Path(image.path).absolute()), image.name
    root = Path(path[: -len(name)]) if path.endswith(name) else Path(path).parent
    return root.name or "dataset"


def plan_map_update(db: MapDatabase, images: Sequence[PosedImage], hashes: Sequence[str]) -> MapUpdatePlan:
    """Decide, per incoming image, whether it is new, kept, updated, replaced or renamed.

    Args:
        db: the (open) map.
        images: incoming records, names unique.
        hashes: SHA-256 of each image file (same order).

    Raises:
        InputError: two incoming images have the same name.
    """
    if len(hashes) != len(images):
        raise InputError(f"plan_map_update: {len(images)} images but {len(hashes)} hashes")
    seen: set[str] = set()
    plan = MapUpdatePlan()
    for image, sha in zip(images, hashes):
        if image.name in seen:
            raise InputError(f"two images of the input are named {image.name!r}; names must be unique")
        seen.add(image.name)
        candidates = [
            image.name,
            f"{_dataset_prefix(image)}/{image.name}",
            f"{_dataset_prefix(image)}-{sha[:8]}/{image.name}",
        ]
        for k, name in enumerate(candidates):
            record = image if name == image.name else dataclasses.replace(image, name=name)
            source = db.image_source(name)
            if source is None:
                plan.add.append((record, sha))
                break
            stored_path, stored_sha = source
            same_path = stored_path is not None and Path(stored_path) == Path(image.path)
            same_content = stored_sha == sha if stored_sha is not None else same_path
            if same_content:
                if _same_record(db.get_posed_image(name), record) and stored_sha is not None:
                    plan.keep.append(name)
                else:
                    plan.update.append((record, sha))
                break
            if same_path or k == len(candidates) - 1:
                plan.replace.append((record, sha))
                break
        if record.name != image.name:
            plan.renamed.append((image.name, record.name))
    return plan
