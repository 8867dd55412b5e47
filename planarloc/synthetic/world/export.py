"""Write a world's map and query sessions to disk in the TUM RGB-D layout.

Layout of ``out_dir``::

    world.json                  generator, format version, preset name, seed, full config
    map/  and  query/           one TUM RGB-D sequence each:
        rgb/<ts>.png            8-bit RGB colour image (ts = timestamp with 6 decimals)
        depth/<ts>.png          16-bit depth, metres x 5000, 0 = no measurement
                                (nothing seen, or beyond 65535 / 5000 = 13.1 m)
        rgb.txt, depth.txt      '# ' comment lines, then 'timestamp filename' per frame
        groundtruth.txt         '# ' comment lines ending with '# timestamp tx ty tz qx qy qz qw',
                                then the camera-to-world pose of the optical frame per frame
                                (quaternion x y z w, as TUM)
        camera.txt              '# ' comment line, then 'PINHOLE width height fx fy cx cy'
        gravity.txt             '# ' comment lines ending with '# timestamp gx gy gz', then the
                                true unit direction of gravity (down) in the camera frame per
                                frame, ``g_cam = R (0, 1, 0)`` for ``cam_from_world`` R (what an
                                ideal IMU would give; (0, 1, 0) for an upright camera)
    COMPLETE                    written last; its presence with an identical world.json
                                means the generation can be reused as is

World frame: y down (gravity), floor at y = 0. Camera frame: x right, y down, z forward.
Intrinsics use the OpenCV pixel convention (top-left pixel centre at (0, 0)).
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from planarloc.synthetic.world.config import WorldConfig
from planarloc.synthetic.world.effects import gravity_in_camera
from planarloc.synthetic.world.presets import get_preset
from planarloc.synthetic.world.sessions import Session, build_sessions, render_frame

logger = logging.getLogger(__name__)

FORMAT_VERSION = 2
"""2: gravity.txt per session."""
DEPTH_SCALE = 5000.0
"""TUM depth PNG scale: stored value = depth in metres x 5000."""
MARKER = "COMPLETE"
_WORKERS = 2  # frames rendered and written concurrently
_PNG = [
    cv2.IMWRITE_PNG_COMPRESSION,
    1,
    cv2.IMWRITE_PNG_STRATEGY,
    cv2.IMWRITE_PNG_STRATEGY_RLE,
]  # fast, lossless


def timestamp_name(timestamp: float) -> str:
    """TUM file stem of a timestamp: 6 decimals, e.g. ``0.100000``."""
    return f"{timestamp:.6f}"


def depth_to_png16(depth: np.ndarray) -> np.ndarray:
    """(H, W) float depth in metres (0 or inf = none) to uint16 TUM depth (0 = none, also beyond 13.1 m)."""
    d = np.asarray(depth, dtype=np.float64)
    scaled = np.rint(np.where(np.isfinite(d) & (d > 0), d, 0.0) * DEPTH_SCALE)
    scaled[scaled > np.iinfo(np.uint16).max] = 0
    return scaled.astype(np.uint16)


def groundtruth_lines(timestamps: np.ndarray, R: np.ndarray, t: np.ndarray) -> list[str]:
    """TUM lines ``ts tx ty tz qx qy qz qw`` (camera-to-world) of (N,) timestamps and ``cam_from_world``
    poses given as (N, 3, 3) rotations R and (N, 3) translations t."""
    R = np.asarray(R, dtype=np.float64)
    world_from_cam_R = np.transpose(R, (0, 2, 1))
    centers = -np.einsum("nij,nj->ni", world_from_cam_R, np.asarray(t, dtype=np.float64))
    quats = Rotation.from_matrix(world_from_cam_R).as_quat(canonical=True)  # x, y, z, w with w >= 0
    return [
        f"{timestamp_name(ts)} " + " ".join(f"{v:.9f}" for v in (*c, *q))
        for ts, c, q in zip(timestamps, centers, quats, strict=True)
    ]


def _write_text(path: Path, header: list[str], lines: list[str]) -> None:
    path.write_text("".join(f"# {h}\n" for h in header) + "".join(f"{line}\n" for line in lines))


def _write_session_meta(session: Session, folder: Path, label: str) -> None:
    names = [timestamp_name(ts) for ts in session.timestamps]
    _write_text(
        folder / "rgb.txt", ["color images", label, "timestamp filename"], [f"{n} rgb/{n}.png" for n in names]
    )
    _write_text(
        folder / "depth.txt",
        ["depth maps (uint16, metres x 5000, 0 = invalid)", label, "timestamp filename"],
        [f"{n} depth/{n}.png" for n in names],
    )
    _write_text(
        folder / "groundtruth.txt",
        [
            (
                "ground truth trajectory: camera-to-world pose of the camera optical frame "
                "(x right, y down, z forward)"
            ),
            "world frame: y down (gravity), floor at y = 0; " + label,
            "timestamp tx ty tz qx qy qz qw",
        ],
        groundtruth_lines(session.timestamps, session.R, session.t),
    )
    gravity = gravity_in_camera(session.R)
    _write_text(
        folder / "gravity.txt",
        [
            "true gravity direction (down, unit) in the camera frame (x right, y down, z forward)",
            "world frame: y down, so g_cam = R (0, 1, 0) for cam_from_world R; " + label,
            "timestamp gx gy gz",
        ],
        [f"{n} " + " ".join(f"{v:.12f}" for v in g) for n, g in zip(names, gravity, strict=True)],
    )
    K = session.K
    _write_text(
        folder / "camera.txt",
        ["PINHOLE width height fx fy cx cy (COLMAP model syntax, OpenCV pixel centres at integers)"],
        [
            "PINHOLE {} {} {!r} {!r} {!r} {!r}".format(
                session.width, session.height, *(float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
            )
        ],
    )


def read_gravity(path: str | Path) -> dict[str, np.ndarray]:
    """The ``gravity.txt`` of an exported session: ``{timestamp name: (3,) unit gravity in the camera}``.

    Raises:
        ValueError: naming the file and line of a malformed row.
    """
    path = Path(path)
    out: dict[str, np.ndarray] = {}
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split()
        try:
            g = np.array([float(v) for v in parts[1:]])
        except ValueError:
            g = np.zeros(0)
        if len(parts) != 4 or not np.all(np.isfinite(g)) or not np.linalg.norm(g) > 0:
            raise ValueError(
                f"{path}:{number}: expected 'timestamp gx gy gz' with a non-zero direction, got {line!r}"
            )
        out[parts[0]] = g / np.linalg.norm(g)
    return out


def _write_frame(session: Session, index: int, folder: Path) -> None:
    image, depth = render_frame(session, index)
    name = timestamp_name(session.timestamps[index])
    if not cv2.imwrite(str(folder / "rgb" / f"{name}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR), _PNG):
        raise OSError(f"could not write {folder / 'rgb' / name}.png")
    if not cv2.imwrite(str(folder / "depth" / f"{name}.png"), depth_to_png16(depth), _PNG):
        raise OSError(f"could not write {folder / 'depth' / name}.png")


def _describe(config: WorldConfig, seed: int) -> str:
    doc = {
        "generator": "planarloc.synthetic.world",
        "format_version": FORMAT_VERSION,
        "preset": config.name,
        "seed": int(seed),
        "config": config.to_dict(),
    }
    return json.dumps(doc, indent=2, sort_keys=True) + "\n"


def is_complete(out_dir: str | Path, config: WorldConfig, seed: int) -> bool:
    """True if ``out_dir`` holds a finished generation of exactly this config and seed."""
    out = Path(out_dir)
    world_json = out / "world.json"
    if not (out / MARKER).is_file() or not world_json.is_file():
        return False
    return world_json.read_text() == _describe(config, seed)


def generate(
    preset_name_or_config: str | WorldConfig,
    out_dir: str | Path,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Render a world's map and query sessions into ``out_dir`` (layout in the module docstring).

    Args:
        preset_name_or_config: a preset name (see ``presets.preset_names()``) or a WorldConfig.
        out_dir: target folder, created if needed. Files of an older or different generation
            there (world.json, COMPLETE, map/, query/) are replaced; nothing else is touched.
        seed: non-negative integer; the same (config, seed) gives the same bytes.
        progress: optional callable ``(done, total)`` called after each written frame.

    Returns:
        ``out_dir`` as a Path. If it already holds a complete generation of the same config
        and seed, nothing is rendered.

    Raises:
        ValueError: unknown preset, bad config or seed.
    """
    config = (
        get_preset(preset_name_or_config) if isinstance(preset_name_or_config, str) else preset_name_or_config
    )
    if not isinstance(config, WorldConfig):
        raise ValueError(  # noqa: TRY004 - bad config is a ValueError throughout this package
            f"expected a preset name or a WorldConfig, got {type(preset_name_or_config).__name__}"
        )
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    seed = int(seed)
    out = Path(out_dir)
    if is_complete(out, config, seed):
        logger.info("reusing world %r (seed %d) in %s", config.name, seed, out)
        return out
    map_session, query_session = build_sessions(config, seed)
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).unlink(missing_ok=True)
    (out / "world.json").unlink(missing_ok=True)
    for name in ("map", "query"):
        if (out / name).exists():
            shutil.rmtree(out / name)
    (out / "world.json").write_text(_describe(config, seed))
    total = len(map_session) + len(query_session)
    logger.info("generating world %r (seed %d): %d frames into %s", config.name, seed, total, out)
    jobs = []
    for session in (map_session, query_session):
        folder = out / session.name
        (folder / "rgb").mkdir(parents=True)
        (folder / "depth").mkdir()
        _write_session_meta(
            session, folder, f"planarloc synthetic world {config.name!r}, seed {seed}, session {session.name}"
        )
        jobs += [(session, index, folder) for index in range(len(session))]
    # Frames are independent (each has its own noise generator), so two workers give the same
    # bytes as one; OpenCV and large numpy operations release the GIL, so they overlap.
    with ThreadPoolExecutor(max_workers=_WORKERS) as pool:
        for done, _ in enumerate(pool.map(lambda job: _write_frame(*job), jobs), start=1):
            if progress is not None:
                progress(done, total)
    (out / MARKER).write_text("complete\n")
    return out
