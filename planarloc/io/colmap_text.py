"""COLMAP sparse models in text form (``cameras.txt`` + ``images.txt``).

``cameras.txt``: one line per camera, ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...`` with MODEL
one of ``SIMPLE_PINHOLE``, ``PINHOLE``, ``OPENCV`` (other COLMAP models are rejected with an
error naming the model; undistort the images first, e.g. with ``colmap image_undistorter``).

``images.txt``: two lines per image, ``#`` comment lines anywhere::

    IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME     (cam_from_world, as in COLMAP)
    X Y POINT3D_ID X Y POINT3D_ID ...                 (2D points, ignored; may be empty)

Images are found at ``image_dir / NAME``. ``points3D.txt`` is not read: planarloc needs no 3D
model. Images are returned sorted by NAME with ``index`` = rank (COLMAP ids are arbitrary).

Gravity: the format does not define the world's up axis (``world_down`` is None): the map
estimates it from its poses, or the user gives it with the dataset option ``up=``.
"""

from __future__ import annotations

from pathlib import Path

from planarloc.geometry.camera import Camera
from planarloc.io.camera_file import read_camera_file
from planarloc.io.format_error import FormatError
from planarloc.io.lines import parse_int, parse_pose_fields, read_text, resolve_image
from planarloc.io.text import WXYZ_T
from planarloc.map.posed_image import PosedImage

FORMAT = "COLMAP text model"


def read_colmap_cameras(path: Path) -> dict[int, Camera]:
    """``{camera_id: Camera}`` of a COLMAP ``cameras.txt``."""
    cams = read_camera_file(path, FORMAT)
    out: dict[int, Camera] = {}
    for key, cam in cams.items():
        if key is None:
            raise FormatError(
                path,
                None,
                "expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', found a line without CAMERA_ID",
            )
        try:
            # COLMAP puts the top-left pixel centre at (0.5, 0.5); planarloc uses OpenCV's (0, 0).
            out[int(key)] = cam.with_principal_point_offset(-0.5, -0.5)
        except ValueError:
            raise FormatError(path, None, f"expected integer camera ids, found {key!r}") from None
    return out


def _default_image_dir(root: Path) -> Path:
    for cand in (root / "images", root.parent / "images", root.parent.parent / "images"):
        if cand.is_dir():
            return cand
    raise FormatError(
        root,
        None,
        "no image directory given and none found at images/, ../images/ or ../../images/; pass image_dir=",
    )


def read_colmap(root: Path, *, image_dir: Path | None = None, check_images: bool = True) -> list[PosedImage]:
    """Read the posed images of a COLMAP text model (format in the module docstring).

    Args:
        root: the model directory (``cameras.txt``, ``images.txt``), e.g. ``sparse/0``.
        image_dir: directory the image NAMEs are relative to; default the first existing of
            ``root/images``, ``root/../images``, ``root/../../images``.
        check_images: raise if an image does not exist.

    Returns:
        :class:`PosedImage` records sorted by name, ``index`` = rank in that order.

    Raises:
        FormatError: missing files/images, malformed lines, unsupported camera models,
            unknown camera ids.
    """
    root = Path(root)
    cameras = read_colmap_cameras(root / "cameras.txt")
    images_path = root / "images.txt"
    text = read_text(
        images_path, FORMAT, "two lines per image, 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME' + 2D points"
    )
    img_root = Path(image_dir) if image_dir is not None else _default_image_dir(root)

    records = []
    names: dict[str, int] = {}
    expect_points = False
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if line.startswith("#"):
            continue
        tokens = line.split()
        if expect_points:
            expect_points = False
            # The 2D-point line of the previous image (possibly empty) is ignored; some writers
            # omit the empty line, so a line that cannot be 'X Y POINT3D_ID' triples is a pose line.
            if len(tokens) % 3 == 0:
                continue
        if not line:
            continue
        if len(tokens) < 10:
            raise FormatError(
                images_path,
                lineno,
                f"expected 10 fields 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', found {len(tokens)}",
            )
        parse_int(images_path, lineno, tokens[0], "IMAGE_ID", 1)
        pose = parse_pose_fields(images_path, lineno, tokens[1:8], WXYZ_T, 2)
        cam_id = parse_int(images_path, lineno, tokens[8], "CAMERA_ID", 9)
        if cam_id not in cameras:
            raise FormatError(images_path, lineno, f"expected a CAMERA_ID of cameras.txt, found {cam_id}")
        name = " ".join(tokens[9:])
        if name in names:
            raise FormatError(
                images_path, lineno, f"expected unique image names, found {name!r} again (line {names[name]})"
            )
        names[name] = lineno
        path = resolve_image(images_path, lineno, img_root, name, check=check_images)
        records.append((name, path, pose, cameras[cam_id]))
        expect_points = True
    if not records:
        raise FormatError(images_path, None, "expected at least one image, found none")
    records.sort(key=lambda r: r[0])
    return [
        PosedImage(name=name, path=path, cam_from_world=pose, camera=cam, index=i)
        for i, (name, path, pose, cam) in enumerate(records)
    ]
