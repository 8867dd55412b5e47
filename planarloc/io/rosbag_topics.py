"""Which topics of a bag are read: the image, CameraInfo and pose topics, given by the user or
found by their message types (:mod:`planarloc.io.rosbag` reads them)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, overload

from planarloc.io.format_error import FormatError


@overload
def pick_topic(
    topics: dict[str, str],
    wanted: str | None,
    types: Sequence[str],
    option: str,
    root: Path,
    required: Literal[True],
) -> str: ...
@overload
def pick_topic(
    topics: dict[str, str], wanted: str | None, types: Sequence[str], option: str, root: Path, required: bool
) -> str | None: ...
def pick_topic(
    topics: dict[str, str], wanted: str | None, types: Sequence[str], option: str, root: Path, required: bool
) -> str | None:
    """The topic of one of ``types`` to read: ``wanted`` (checked), else the bag's only one; None
    when there is none and the topic is not ``required`` (FormatError otherwise, naming ``option``)."""
    if wanted is not None:
        if wanted not in topics:
            raise FormatError(root, None, f"{option}={wanted!r}: no such topic; topics: {topic_list(topics)}")
        if topics[wanted] not in types:
            raise FormatError(
                root,
                None,
                f"{option}={wanted!r} has type {topics[wanted]}, expected one of {', '.join(types)}",
            )
        return wanted
    candidates = sorted(t for t, ty in topics.items() if ty in types)
    if len(candidates) == 1:
        return candidates[0]
    if not required and not candidates:
        return None
    found = ", ".join(candidates) if candidates else "none"
    raise FormatError(
        root, None, f"give the dataset option {option}=TOPIC ({', '.join(types)} topics in the bag: {found})"
    )


def topic_list(topics: dict[str, str]) -> str:
    """``topic (type), ...`` of a bag's topics, for an error message."""
    return ", ".join(f"{t} ({ty})" for t, ty in sorted(topics.items())) or "none"


@dataclass(frozen=True)
class BagTopics:
    """The topics read: images, CameraInfo (None when the camera is given) and poses (None: tf or none)."""

    image: str
    camera_info: str | None
    pose: str | None
