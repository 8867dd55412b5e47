"""Fleet sessions: the table's bounds on a fake clock, then robots streaming to a real server (one
stream per robot kept in one worker, frames in order, evictions with a clear 410, concurrent
frames of one session, a killed worker), and the client's Session."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from record_schemas import check
from served import Served, serving

from planarloc.cli.main import main
from planarloc.client import Client, ServiceError, SessionRestarted
from planarloc.geometry.pose import Pose
from planarloc.io.tum import read_tum_trajectory
from planarloc.serve.launcher import worker_pids
from planarloc.serve.requests import LocalizeRequest, RequestError
from planarloc.serve.sessions import SessionGone, SessionTable


# ---- the table, on a fake clock ------------------------------------------------------------------------
class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def frame(session: str, structure: str | None = None) -> LocalizeRequest:  # a frame's fields, no image
    return LocalizeRequest("m", "f.png", b"", None, session=session, stamp=1.0, structure=structure)


def test_the_table_bounds_sessions_in_number_and_idle_time() -> None:
    clock = Clock()
    table = SessionTable(slots=2, max_sessions=3, idle_s=10.0, clock=clock)
    entries = [table.open(frame(f"r{i}"), [True, True]) for i in range(3)]
    assert [e.slot for e in entries] == [0, 1, 0]  # the worker with the fewest sessions
    for e in entries:
        table.done(e, True)
    clock.t = 1.0
    table.done(table.open(frame("r0"), [True, True]), True)  # r0 used: r1 is now the least recently used
    fourth = table.open(frame("r3"), [True, True])
    assert fourth.slot == 1 and table.count == 3
    assert [d.id for d in table.take_drops()] == ["r1"]
    with pytest.raises(SessionGone, match="least recently used") as exc:
        table.open(frame("r1"), [True, True])
    assert exc.value.status == 410
    table.done(table.open(frame("r1"), [True, True]), True)  # the next request starts a new stream
    # A session with a frame in progress is never evicted; with all busy a new one waits (503).
    busy = SessionTable(slots=1, max_sessions=1, clock=clock)
    busy.open(frame("a"), [True])
    with pytest.raises(RequestError) as exc:
        busy.open(frame("b"), [True])
    assert exc.value.status == 503 and exc.value.retry_after_s == 1
    # Idle eviction.
    clock.t = 30.0
    table.evict_idle()
    with pytest.raises(SessionGone, match="without a frame"):
        table.open(frame("r0"), [True, True])
    # A frame cannot change its session's settings; a worker's death loses its sessions.
    s = table.open(frame("x"), [False, True])
    assert s.slot == 1
    table.done(s, True)
    with pytest.raises(RequestError, match="cannot change") as exc:
        table.open(frame("x", structure="none"), [True, True])
    assert exc.value.status == 409
    table.lose_slot(1, "was lost: the worker process serving it died")
    with pytest.raises(SessionGone, match="worker process serving it died"):
        table.open(frame("x"), [True, True])
    assert table.evicted["limit"] == 2 and table.evicted["idle"] >= 1 and table.evicted["worker_died"] >= 1


# ---- robots on a real server ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fleet(served_world) -> Iterator[Served]:
    options = ["--workers", "2", "--queue", "6", "--max-sessions", "3", "--session-idle", "6"]
    with serving(served_world, options) as served:
        yield served


def stream(world: Path) -> list[tuple[float, Path, Pose]]:
    """(stamp, image, ground-truth cam_from_world) of the query frames, in order."""
    images = sorted((world / "query" / "rgb").glob("*.png"))
    stamps = [
        float(line.split()[0])
        for line in (world / "query" / "rgb.txt").read_text().splitlines()
        if line and line[0] != "#"
    ]
    times, world_from_cam = read_tum_trajectory(world / "query" / "groundtruth.txt")
    truth = {round(float(t), 6): p.inverse() for t, p in zip(times, world_from_cam)}
    return [(t, im, truth[round(t, 6)]) for t, im in zip(stamps, images)]


def post_frame(
    url: str, image: Path, stamp: float, session: str, camera: str, **extra: str
) -> httpx.Response:
    return httpx.post(
        url + "/v1/localize",
        files={"image": (image.name, image.read_bytes())},
        data={"camera": camera, "session": session, "stamp": repr(stamp), **extra},
        timeout=120,
    )


def test_a_robot_streams_its_frames_and_gets_the_sequence_record(fleet, tmp_path) -> None:
    """The session's answers are the records of `planarloc localize --sequence` on the same frames."""
    frames = stream(fleet.world)
    listing = tmp_path / "frames.txt"
    listing.write_text("".join(f"{t!r} {image}\n" for t, image, _ in frames))
    out = tmp_path / "poses.txt"
    odometry = fleet.world / "query" / "groundtruth.txt"  # the true motion as wheel odometry
    assert (
        main(
            [
                "localize",
                "--map",
                str(fleet.map_path),
                "--sequence",
                str(listing),
                "--odometry",
                str(odometry),
                "--camera",
                fleet.camera,
                "--fixes",
                "wait",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    local = [
        json.loads((tmp_path / "poses.txt.json.d" / f"{image.name}.json").read_text())
        for _, image, _ in frames
    ]
    with Client(fleet.url) as client:
        robot = client.session("robot-a", camera=fleet.camera)
        records = [robot.localize(image, stamp, odometry=truth) for stamp, image, truth in frames]
    assert [r["session"]["frame"] for r in records] == list(
        range(1, len(frames) + 1)
    )  # one stream, one worker
    for rec, loc in zip(records, local):  # one record schema for the CLI's frames and the service's
        check("record", rec, "session answer")
        check("record", loc, "localize --sequence record")
    for rec, loc, (_, _, truth) in zip(records, local, frames):
        assert rec["session"]["id"] == "robot-a" and rec["name"] == loc["name"]
        assert rec["status"] == loc["status"] and rec["status"] in ("localized", "predicted", "lost")
        assert rec["motion_source"] == loc["motion_source"] and rec["fix_status"] == loc["fix_status"]
        if rec["success"]:
            np.testing.assert_allclose(rec["quat_wxyz"], loc["quat_wxyz"], atol=1e-6)
            np.testing.assert_allclose(rec["t"], loc["t"], atol=1e-6)
            np.testing.assert_allclose(
                np.array(rec["covariance_xyz_rotvec"], float),
                np.array(loc["covariance_xyz_rotvec"], float),
                rtol=1e-4,
                atol=1e-9,
            )
            assert (
                np.linalg.norm(Pose.from_quat_wxyz(rec["quat_wxyz"], rec["t"]).center - truth.center) < 0.25
            )
    assert all(r["status"] == "localized" for r in records) and robot.restarts == 0
    # Out of order: refused (409), the stream unchanged.
    r = post_frame(fleet.url, frames[0][1], frames[0][0], "robot-a", fleet.camera, structure="tracks")
    assert r.status_code == 409 and "time order" in check("service-error", r.text)["error"]
    r = post_frame(fleet.url, frames[0][1], frames[-1][0] + 1, "robot-a", fleet.camera)
    assert r.status_code == 200 and r.json()["session"]["frame"] == len(frames) + 1
    # A frame cannot change the session's settings; odometry is a pose; stamp is required.
    r = post_frame(fleet.url, frames[0][1], frames[-1][0] + 2, "robot-a", fleet.camera, structure="none")
    assert r.status_code == 409 and "cannot change" in r.json()["error"]
    for extra, status in [({"odometry": "1 2 3"}, 400), ({"odometry": "0 0 0 0 0 0 1"}, 200)]:
        r = post_frame(
            fleet.url,
            frames[1][1],
            frames[-1][0] + 3 + len(extra["odometry"]),
            "robot-b",
            fleet.camera,
            **extra,
        )
        assert r.status_code == status, r.text
    r = httpx.post(
        fleet.url + "/v1/localize",
        files={"image": ("a.png", frames[0][1].read_bytes())},
        data={"camera": fleet.camera, "session": "robot-c"},
        timeout=60,
    )
    assert r.status_code == 400 and "stamp" in r.json()["error"]


def test_concurrent_frames_of_one_session_are_safe(fleet) -> None:
    frames = stream(fleet.world)[:4]
    answers: list[httpx.Response] = []
    lock = threading.Lock()

    def send(stamp: float, image: Path) -> None:
        r = post_frame(fleet.url, image, stamp, "robot-concurrent", fleet.camera)
        with lock:
            answers.append(r)

    threads = [threading.Thread(target=send, args=(stamp, image)) for stamp, image, _ in frames]
    for t in threads:
        t.start()
    for t in threads:
        t.join(180)
    codes = sorted(r.status_code for r in answers)
    assert len(codes) == 4 and set(codes) <= {200, 409}, [r.text for r in answers]
    done = sorted(r.json()["session"]["frame"] for r in answers if r.status_code == 200)
    assert done == list(range(1, len(done) + 1))  # each frame once, in one stream
    stamps = [r.json()["stamp"] for r in answers if r.status_code == 200]
    assert stamps == sorted(stamps) or len(set(stamps)) == len(stamps)


def test_evicted_and_lost_sessions_get_a_clear_410(fleet) -> None:
    stamp, image, _ = stream(fleet.world)[0]
    # max 3 sessions: a fourth evicts the least recently used.
    for robot in ("e1", "e2", "e3", "e4"):
        time.sleep(0.05)
        assert post_frame(fleet.url, image, stamp, robot, fleet.camera).status_code == 200
    r = post_frame(fleet.url, image, stamp + 1, "e1", fleet.camera)
    assert r.status_code == 410 and "least recently used" in r.json()["error"]
    assert post_frame(fleet.url, image, stamp + 2, "e1", fleet.camera).json()["session"]["frame"] == 1
    # Idle for more than 6 s: evicted by the server's sweep.
    time.sleep(9)
    metrics = httpx.get(fleet.url + "/metrics").text
    assert (
        "planarloc_sessions 0.0" in metrics and 'planarloc_sessions_evicted_total{reason="idle"}' in metrics
    )
    r = post_frame(fleet.url, image, stamp + 3, "e4", fleet.camera)
    assert r.status_code == 410 and "without a frame" in r.json()["error"]
    # Its worker killed: the session is lost, and says so.
    with Client(fleet.url) as client:
        robot = client.session("k1", camera=fleet.camera)
        robot.localize(image, stamp)
        for pid in worker_pids(fleet.process.pid):
            os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 90
        while httpx.get(fleet.url + "/healthz").json()["workers_alive"] < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
        with pytest.raises(SessionRestarted, match="worker process serving it died"):
            robot.localize(image, stamp + 1)
        assert robot.restarts == 1
        assert robot.localize(image, stamp + 2)["session"]["frame"] == 1
        with pytest.raises(ServiceError) as exc:
            robot.localize(image, stamp + 1)  # out of order
        assert exc.value.status == 409
