"""Sessions against hostile and unlucky clients: ids anchored at the very end (no trailing newline),
a frame stamped far in the future refused without locking its session, idle eviction that counts only
accepted frames, black and featureless frames answered with their status while the session goes on;
and the request checks around them (the bearer scheme in any case, integer image sizes, the one
pixel cap) on a real server."""

from __future__ import annotations

import struct
import time
import zlib
from collections.abc import Iterator
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from served import Served, serving

from planarloc.localize.localizer import Localizer
from planarloc.serve.app import bearer_token_matches
from planarloc.serve.requests import (
    MAP_NAME,
    MAX_STAMP_AHEAD_S,
    SEED,
    SESSION,
    STAMP,
    LocalizeRequest,
    MapSet,
    RequestError,
    parse_localize_request,
)
from planarloc.serve.sessions import MAX_FRAME_GAP_S, SessionGone, SessionStates, SessionTable
from planarloc.serve.worker import session_frame_with

TOKEN = "session-token"
NOW = 1_700_000_000.0


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def png(pixels: np.ndarray) -> bytes:
    return cv2.imencode(".png", pixels)[1].tobytes()


def blank_and_featureless() -> dict[str, bytes]:
    return {
        "black": png(np.zeros((240, 320), np.uint8)),
        "gradient": png(np.tile(np.linspace(0, 255, 320), (240, 1)).astype(np.uint8)),
    }


def png_bomb() -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", 30000, 30000, 8, 0, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(b"\0" * 30001 * 4))
        + chunk(b"IEND", b"")
    )


# ---- request checks, no server ------------------------------------------------------------------------
def test_ids_and_fields_are_anchored_at_the_very_end(tmp_path: Path) -> None:
    """`$` also matches before a final newline: "robot-1\\n" would be another id than "robot-1"."""
    for pattern, good in ((SESSION, "robot-1"), (MAP_NAME, "office"), (SEED, "5"), (STAMP, "1.5")):
        assert pattern.match(good) and not pattern.match(good + "\n") and not pattern.match(good + "\n\n")
    (tmp_path / "m.db").write_bytes(b"x")
    maps = MapSet.from_specs([f"m={tmp_path / 'm.db'}"])
    image = png(np.zeros((24, 32), np.uint8))
    for fields, match in [
        ({"session": "robot-1\n", "stamp": "1"}, "session: expected"),
        ({"seed": "5\n"}, "seed: expected"),
    ]:
        with pytest.raises(RequestError, match=match) as exc:
            parse_localize_request(fields, image, "q.png", maps)
        assert exc.value.status == 400
    with pytest.raises(ValueError, match="map names"):
        MapSet.from_specs([f"m\n={tmp_path / 'm.db'}"])
    with pytest.raises(RequestError, match="the file is empty"):
        parse_localize_request({}, b"", "q.png", maps)


def test_a_stamp_far_ahead_of_the_servers_clock_is_refused(tmp_path: Path) -> None:
    (tmp_path / "m.db").write_bytes(b"x")
    maps = MapSet.from_specs([f"m={tmp_path / 'm.db'}"])
    image = png(np.zeros((24, 32), np.uint8))
    ok = parse_localize_request({"session": "r", "stamp": repr(NOW + 60)}, image, "q.png", maps, now=NOW)
    assert ok.stamp == NOW + 60  # clocks differ a little: fine
    assert (
        parse_localize_request({"session": "r", "stamp": "0.1"}, image, "q.png", maps, now=NOW).stamp == 0.1
    )
    for stamp in (NOW + MAX_STAMP_AHEAD_S + 1, 1e11, 9.9e11):
        with pytest.raises(RequestError, match="ahead of the server's clock.*session is unchanged") as exc:
            parse_localize_request({"session": "r", "stamp": repr(stamp)}, image, "q.png", maps, now=NOW)
        assert exc.value.status == 400


def test_bearer_scheme_is_case_insensitive_and_the_token_exact() -> None:
    for header in ("Bearer tok", "bearer tok", "BEARER tok", "bEaReR   tok", " Bearer tok "):
        assert bearer_token_matches(header, "tok"), header
    for header in (
        "",
        "Bearer",
        "Bearer ",
        "Bearertok",
        "Bearer TOK",
        "Bearer tok2",
        "Basic tok",
        "tok",
        "Bearer\ttok",
        "Bearer tok tok",
    ):
        assert not bearer_token_matches(header, "tok"), header


# ---- the session table: only accepted frames count -------------------------------------------------------
def frame(session: str) -> LocalizeRequest:
    return LocalizeRequest("m", "f.png", b"", None, session=session, stamp=1.0)


def test_refused_frames_neither_keep_a_session_alive_nor_make_it_recent() -> None:
    clock = Clock()
    table = SessionTable(slots=1, max_sessions=2, idle_s=10.0, clock=clock)
    table.done(table.open(frame("a"), [True]), True)
    clock.t = 1.0
    table.done(table.open(frame("b"), [True]), True)
    for t in range(2, 10):  # a's client keeps sending frames its session refuses (e.g. 409)
        clock.t = float(t)
        table.done(table.open(frame("a"), [True]), False)
    table.done(table.open(frame("c"), [True]), True)  # the table is full: the least recently *answered* goes
    with pytest.raises(SessionGone, match="least recently used"):
        table.open(frame("a"), [True])
    # Idle time: b's last accepted frame was at t = 1; refused frames after it do not count.
    clock.t = 10.5
    table.done(table.open(frame("b"), [True]), False)
    clock.t = 11.5
    with pytest.raises(SessionGone, match="after 10 s without a frame"):
        table.open(frame("b"), [True])


# ---- a session's stream, in process -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def localizer(served_world) -> Localizer:
    return Localizer(served_world[1])


def test_a_session_goes_on_after_bad_frames_and_stamps(localizer: Localizer, served_world) -> None:
    world, _map_path, _camera = served_world
    images = [p.read_bytes() for p in sorted((world / "query" / "rgb").glob("*.png"))]
    states = SessionStates()

    def send(data: bytes, stamp: float) -> dict:
        return session_frame_with(
            localizer, states, LocalizeRequest("office", "f.png", data, None, session="r", stamp=stamp), 1
        )

    assert send(images[0], 0.0)["session"]["frame"] == 1
    for k, (name, data) in enumerate(blank_and_featureless().items(), start=1):
        record = send(data, 0.1 * k)  # the issue: IndexError, a 500 and a closed session
        assert record["status"] == "lost" and not record["success"], name
        assert record["session"]["frame"] == k + 1
    with pytest.raises(RequestError, match=f"more than {MAX_FRAME_GAP_S:g} s.*session goes on") as exc:
        send(images[1], 0.2 + MAX_FRAME_GAP_S + 1)
    assert exc.value.status == 409
    for data, match in [
        (b"", "the image is empty"),
        (images[1][:500], "truncated PNG"),
        (png_bomb(), "30000x30000"),
    ]:
        with pytest.raises(RequestError, match=match) as exc:
            send(data, 0.3)
        assert 400 <= exc.value.status < 500
    record = send(images[3], 0.3)
    assert record["session"]["frame"] == 4 and record["status"] in ("localized", "predicted", "lost")
    assert send(images[4], 0.4)["session"]["frame"] == 5


# ---- on a real server --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def served(served_world) -> Iterator[Served]:
    options = ["--workers", "1", "--queue", "4", "--token", TOKEN, "--session-idle", "3"]
    with serving(served_world, options, TOKEN) as served:
        yield served


def post(server: Served, image: bytes, auth: str = f"Bearer {TOKEN}", **fields: str) -> httpx.Response:
    return httpx.post(
        server.url + "/v1/localize",
        files={"image": ("f.png", image)},
        data={"camera": server.camera, **fields},
        headers={"Authorization": auth},
        timeout=120,
    )


def query_pngs(server: Served) -> list[bytes]:
    return [p.read_bytes() for p in sorted((server.world / "query" / "rgb").glob("*.png"))]


def test_bad_frames_and_future_stamps_leave_the_session_running(served) -> None:
    images = query_pngs(served)
    now = time.time()
    sent = [post(served, images[0], session="robot-1", stamp="0.0")]
    for k, data in enumerate(blank_and_featureless().values(), start=1):
        sent.append(post(served, data, session="robot-1", stamp=f"{0.1 * k:.1f}"))
    assert [r.status_code for r in sent] == [200, 200, 200], [r.text for r in sent]
    assert [r.json()["status"] for r in sent[1:]] == ["lost", "lost"]
    refused = [
        post(served, images[1], session="robot-1", stamp=repr(now + 10 * MAX_STAMP_AHEAD_S)),
        post(served, images[1], session="robot-1", stamp="1e11"),
        post(served, images[1], session="robot-1", stamp=repr(1e6)),  # before now, but an age after 0.2
        post(served, b"", session="robot-1", stamp="0.25"),
        post(served, png_bomb(), session="robot-1", stamp="0.25"),
        post(served, images[1], session="robot-1\n", stamp="0.25"),
    ]
    assert [r.status_code for r in refused] == [400, 400, 409, 400, 413, 400], [r.text for r in refused]
    assert "ahead of the server's clock" in refused[0].json()["error"]
    assert "30000x30000 pixels, over the limit" in refused[4].json()["error"]
    after = [post(served, images[k], session="robot-1", stamp=f"0.{k}") for k in (3, 4)]
    assert [r.status_code for r in after] == [200, 200], [r.text for r in after]
    assert [r.json()["session"]["frame"] for r in after] == [4, 5]  # the same stream


def test_a_session_fed_only_refused_frames_is_evicted(served) -> None:
    images = query_pngs(served)
    assert post(served, images[0], session="robot-2", stamp="5.0").status_code == 200
    accepted = time.monotonic()
    while True:  # idle 3 s: out-of-order frames every 0.3 s (each refused, 409) must not keep it
        r = post(served, images[1], session="robot-2", stamp="1.0")
        if r.status_code != 409:
            break
        assert time.monotonic() - accepted < 20, "refused frames keep the session from being evicted"
        time.sleep(0.3)
    assert r.status_code == 410 and "without a frame" in r.json()["error"]
    assert time.monotonic() - accepted > 3
    assert (
        post(served, images[1], session="robot-2", stamp="1.0").json()["session"]["frame"] == 1
    )  # a new stream


def test_the_bearer_scheme_in_any_case_and_integer_sizes(served) -> None:
    image = query_pngs(served)[0]
    for auth, status in [
        (f"bearer {TOKEN}", 200),
        (f"BEARER  {TOKEN}", 200),
        (f"Bearer {TOKEN.upper()}", 401),
        (f"Basic {TOKEN}", 401),
        (f"Bearer{TOKEN}", 401),
    ]:
        assert httpx.get(served.url + "/v1/maps", headers={"Authorization": auth}).status_code == status, auth
    assert post(served, image, auth=f"bearer {TOKEN}").status_code == 200
    camera = served.camera.split()
    for width in (f"{camera[1]}.5", "1241.5"):
        r = httpx.post(
            served.url + "/v1/localize",
            files={"image": ("f.png", image)},
            data={"camera": " ".join([camera[0], width, *camera[2:]])},
            headers={"Authorization": f"Bearer {TOKEN}"},
            timeout=60,
        )
        assert r.status_code == 400 and "camera" in r.json()["error"] and "whole pixel" in r.json()["error"]
