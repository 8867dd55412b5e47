"""The service configures a request like the library: its defaults are :class:`LocalizerConfig`'s
(a changed library default cannot silently diverge), a form's method and structure become the
enums once, at the edge, and a request's settings are a named, frozen record."""

from __future__ import annotations

import dataclasses
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from planarloc.localize.localizer import LocalizerConfig
from planarloc.robust.options import Method, Structure
from planarloc.serve.requests import MapSet, QuerySettings, RequestError, parse_localize_request

LOC = LocalizerConfig()


@pytest.fixture
def request_parts(tmp_path: Path) -> tuple[bytes, MapSet]:
    (tmp_path / "m.db").write_bytes(b"x")
    png = cv2.imencode(".png", np.zeros((24, 32), np.uint8))[1].tobytes()
    return png, MapSet.from_specs([str(tmp_path / "m.db")])


def test_the_service_defaults_are_the_librarys(request_parts: tuple[bytes, MapSet]) -> None:
    assert QuerySettings() == QuerySettings(LOC.method, LOC.ransac.structure, LOC.ransac.seed)
    assert QuerySettings().config() == LOC
    png, maps = request_parts
    req = parse_localize_request({}, png, "q.png", maps)
    assert (req.method, req.structure, req.seed) == (None, None, None)
    assert req.settings == QuerySettings() and req.settings.config() == LOC


def test_form_fields_become_enums_once(request_parts: tuple[bytes, MapSet]) -> None:
    png, maps = request_parts
    req = parse_localize_request({"method": "2p1p", "structure": "none", "seed": "7"}, png, "q.png", maps)
    assert req.method is Method.P2P1 and req.structure is Structure.NONE and req.seed == 7
    assert pickle.loads(pickle.dumps(req)) == req  # crosses into worker processes
    config = req.settings.config()
    assert (
        config.method is Method.P2P1 and config.ransac.structure is Structure.NONE and config.ransac.seed == 7
    )
    for fields, match in [
        ({"method": "9p"}, "method: expected one of auto, 2p1p"),
        ({"structure": "Tracks"}, "structure: expected one of none, tracks"),
    ]:
        with pytest.raises(RequestError, match=match) as exc:
            parse_localize_request(fields, png, "q.png", maps)
        assert exc.value.status == 400


def test_settings_are_a_frozen_named_record() -> None:
    settings = QuerySettings(Method.NISTER, Structure.TRACKS, 3)
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.seed = 4  # type: ignore[misc]
    assert str(settings) == "(method, structure, seed) = (5p5p-nister, tracks, 3)"
    assert settings != QuerySettings(Method.NISTER, Structure.TRACKS, 4)
