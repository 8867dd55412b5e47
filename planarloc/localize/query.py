"""Query preparation: what every front door turns its input into, checked once, before any work.

A :class:`Query` is one image ready for the localizer: its gray pixels, its camera (the given
one, else the map's when the map has exactly one camera), its gravity (a unit vector in the
camera frame, or None) and the map images to match it against (None: retrieval). The CLI, the
service and a ROS node only parse their inputs (files, form fields, messages) into the
arguments of :meth:`planarloc.localize.localizer.Localizer.prepare`, which builds the query with
:func:`prepare_query`; the single-frame localizer and the stream localizer both take it.

Every check raises :class:`~planarloc.geometry.validation.InputError` with one line naming the
image: an empty, unreadable, truncated or undecodable image, one declaring more pixels than
:data:`planarloc.features.images.MAX_IMAGE_PIXELS` (refused from its header, before decoding, on
every path: files, bytes, arrays), an image whose size differs from its camera's, a map
with several cameras and no camera given, a bad gravity vector, references that are not in the
map.
"""

from __future__ import annotations

import os
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from planarloc.features.images import decode_gray, read_gray, to_gray
from planarloc.features.retrieval import retrieve_from_pairs
from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import InputError
from planarloc.robust.pair_matches import unit_gravity

#: What an image can be given as: an (H, W) / (H, W, 3) BGR uint8 array, JPEG/PNG bytes, a file.
ImageSource = np.ndarray | bytes | str | os.PathLike


@dataclass(frozen=True, eq=False)
class Query:
    """One query image, prepared (:func:`prepare_query`).

    Attributes:
        name: the query's name (results, pairs files, gravity files).
        image: (H, W) uint8 gray pixels.
        camera: its intrinsics, of the image's size.
        gravity: (3,) unit direction of gravity (down) in the camera frame, or None (mounted like
            the map cameras).
        references: the map images to match against, or None for retrieval.
        camera_from_map: True when ``camera`` is the map's (none was given).
    """

    name: str
    image: np.ndarray
    camera: Camera
    gravity: np.ndarray | None = None
    references: tuple[str, ...] | None = None
    camera_from_map: bool = False


def load_gray(image: ImageSource, name: str = "image") -> np.ndarray:
    """The (H, W) uint8 gray pixels of an array, JPEG/PNG bytes or an image file."""
    if isinstance(image, np.ndarray):
        return to_gray(image)
    if isinstance(image, (bytes, bytearray, memoryview)):
        return decode_gray(bytes(image), name)
    if isinstance(image, (str, os.PathLike)):
        return read_gray(Path(image))
    raise InputError(
        f"{name}: expected an image array, JPEG/PNG bytes or a file path, got {type(image).__name__}"
    )


def prepare_query(
    image: ImageSource,
    camera: Camera | None,
    *,
    map_cameras: Collection[Camera],
    map_names: Collection[str],
    name: str = "query",
    gravity: object | None = None,
    references: Sequence[str] | None = None,
    pairs: Mapping[str, Sequence[str]] | None = None,
    top_n: int | None = None,
) -> Query:
    """Check and prepare one query against a map (module docstring).

    Args:
        image: the query image (array, bytes or file).
        camera: its intrinsics; None: the map's, if the map has exactly one camera.
        map_cameras: the map's distinct cameras.
        map_names: the map's image names (references must be among them).
        name: the query's name.
        gravity: (3,) gravity (down) in the camera frame, any non-zero length, or None.
        references: map images to match against instead of retrieval.
        pairs: an hloc pairs mapping ``{query name: [map names]}`` giving the references
            instead (the first ``top_n`` of this query's).
        top_n: how many references a pairs file gives at most.

    Raises:
        InputError: see the module docstring.
    """
    g = None if gravity is None else unit_gravity("gravity", gravity)  # bad input fails before decoding
    if camera is not None and not isinstance(camera, Camera):
        raise InputError(f"camera: expected a planarloc.Camera, got {type(camera).__name__}")
    if references is not None and pairs is not None:
        raise InputError("references and pairs: give one of them")
    if pairs is not None:
        references = retrieve_from_pairs(dict(pairs), name, *([] if top_n is None else [top_n]))
    if references is not None:
        references = tuple(str(r) for r in references)
        unknown = [r for r in references if r not in map_names]
        if unknown:
            raise InputError(
                f"{name}: references not in the map: {unknown[:3]}{'...' if len(unknown) > 3 else ''}"
            )
    gray = load_gray(image, name)
    height, width = gray.shape[:2]
    from_map = camera is None
    if camera is None:
        cameras = set(map_cameras)
        if len(cameras) != 1:
            raise InputError(f"{name}: the map has {len(cameras)} cameras; give the query's intrinsics")
        camera = next(iter(cameras))
    if (camera.width, camera.height) != (width, height):
        whose = "the map's camera (the query has none of its own)" if from_map else "its camera"
        raise InputError(
            f"{name}: image is {width}x{height} but {whose} is {camera.width}x{camera.height}; "
            "give the intrinsics of this image size"
        )
    return Query(name, gray, camera, g, references, from_map)
