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
