"""Request validation without a server: image headers, cameras, map names."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from planarloc.serve.requests import MapSet, RequestError, image_size, parse_localize_request


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_image_size_reads_the_header(ext: str) -> None:
    image = np.random.default_rng(0).integers(0, 255, (37, 53), dtype=np.uint8)
    data = cv2.imencode(ext, image)[1].tobytes()
    assert image_size(data)[1:] == (53, 37)


@pytest.mark.parametrize(
    "data,status",
    [
        (b"hello world", 415),
        (b"\x89PNG\r\n\x1a\n\0\0", 400),
        (b"\xff\xd8\xff\xe0\x00\x10JFIF\x00", 400),
        (b"", 415),
    ],
)
def test_image_size_rejects_non_images(data: bytes, status: int) -> None:
    with pytest.raises(RequestError) as exc:
        image_size(data)
    assert exc.value.status == status


def test_map_names_never_resolve_to_paths(tmp_path: Path) -> None:
    (tmp_path / "a.db").write_bytes(b"x")
    maps = MapSet.from_specs([str(tmp_path / "a.db"), f"b={tmp_path / 'a.db'}"])
    assert maps.resolve("a") == "a" and maps.resolve("b") == "b"
    for name in ("../a.db", str(tmp_path / "a.db"), "a.db", "c"):
        with pytest.raises(RequestError) as exc:
            maps.resolve(name)
        assert exc.value.status == 404
    with pytest.raises(RequestError, match="required when several maps"):
        maps.resolve(None)
    for bad in (["../x=" + str(tmp_path / "a.db")], [str(tmp_path / "missing.db")], []):
        with pytest.raises(ValueError, match="--map"):
            MapSet.from_specs(bad)


def test_camera_must_fit_the_image(tmp_path: Path) -> None:
    (tmp_path / "m.db").write_bytes(b"x")
    maps = MapSet.from_specs([str(tmp_path / "m.db")])
    png = cv2.imencode(".png", np.zeros((24, 32), np.uint8))[1].tobytes()
    req = parse_localize_request({"camera": "PINHOLE 32 24 30 30 16 12", "seed": "3"}, png, "q.png", maps)
    assert req.map_name == "m" and req.image_size == (32, 24) and req.seed == 3 and req.name == "q.png"
    with pytest.raises(RequestError, match="does not fit"):
        parse_localize_request({"camera": "PINHOLE 64 48 30 30 16 12"}, png, "q.png", maps)
    with pytest.raises(RequestError, match="over the limit") as exc:
        parse_localize_request(
            {"camera": "PINHOLE 32 24 30 30 16 12"}, png, "q.png", maps, max_image_bytes=10
        )
    assert exc.value.status == 413


def test_session_fields(tmp_path: Path) -> None:
    (tmp_path / "m.db").write_bytes(b"x")
    maps = MapSet.from_specs([str(tmp_path / "m.db")])
    png = cv2.imencode(".png", np.zeros((24, 32), np.uint8))[1].tobytes()
    req = parse_localize_request(
        {"session": "r1", "stamp": "0.30000000000000004", "odometry": "1 2 3 0 0 0 1"}, png, "q.png", maps
    )
    assert req.stamp == 0.30000000000000004 and req.session == "r1"
    np.testing.assert_allclose(req.odometry.center, [1, 2, 3])  # cam_from_odom of a camera at (1, 2, 3)
    from planarloc.localize.localizer import LocalizerConfig
    from planarloc.robust.options import Method, RansacOptions, Structure
    from planarloc.serve.requests import QuerySettings

    assert req.settings == QuerySettings(
        Method.AUTO, Structure.TRACKS, RansacOptions().seed
    )  # the defaults, filled in
    assert req.method is None and req.settings.config() == LocalizerConfig()
    for fields, match in [
        ({"session": "r1"}, "stamp: required"),
        ({"stamp": "1"}, "only for a frame of a session"),
        ({"session": "r1", "stamp": "1e400"}, "stamp"),
        ({"session": "r1", "stamp": "0x1"}, "stamp"),
        ({"session": "r 1", "stamp": "1"}, "session"),
        ({"session": "r1", "stamp": "1", "odometry": "0 0 0 0 0 0 2"}, "odometry"),
        ({"seed": "²"}, "seed"),
    ]:
        with pytest.raises(RequestError, match=match) as exc:
            parse_localize_request(fields, png, "q.png", maps)
        assert exc.value.status == 400


def test_whose_fault_an_error_is() -> None:
    import sqlite3

    from planarloc.geometry.validation import InputError
    from planarloc.map.schema import MapCorruptError
    from planarloc.serve.requests import ServerFault, classify_error

    assert classify_error(InputError("q.png: cannot decode"), "q.png").status == 400
    for exc in (
        MapCorruptError("/srv/maps/office.db: image a.png: bad blob"),
        sqlite3.DatabaseError("malformed"),
        OSError(5, "Input/output error", "/srv/maps/office.db"),
        OverflowError("int too large"),
        KeyError("x"),
    ):
        fault = classify_error(exc, "q.png")
        assert isinstance(fault, ServerFault) and fault.public and "/srv" not in fault.public
        assert type(exc).__name__ in fault.detail  # the log gets the details
