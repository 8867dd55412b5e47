"""Faults of the server's side, on a real server: SIGKILLed workers seen at once by /healthz and
/metrics, map files deleted, replaced or written under a running server (refused, never served
from two versions), and a damaged map answered 500, logged, without a path."""

from __future__ import annotations

import os
import shutil
import signal
import sqlite3
import time
from pathlib import Path

import httpx
import pytest

from planarloc.client import Client, ServiceError
from planarloc.io.datasets import read_dataset
from planarloc.map.builder import build_map
from planarloc.serve.launcher import start_server, stop_server, worker_pids


def query_images(world: Path) -> list[Path]:
    return sorted((world / "query" / "rgb").glob("*.png"))


def health(url: str) -> tuple[int, dict]:
    r = httpx.get(url + "/healthz", timeout=10)
    return r.status_code, r.json()


def wait_for(predicate, timeout: float = 90.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.1)
    return False


def metric(url: str, line_start: str) -> float:
    for line in httpx.get(url + "/metrics", timeout=10).text.splitlines():
        if line.startswith(line_start):
            return float(line.rsplit(" ", 1)[1])
    raise AssertionError(f"no metric {line_start}")


def test_killed_workers_are_seen_at_once(served_world) -> None:
    world, map_path, camera = served_world
    url, proc = start_server(["--map", str(map_path), "--workers", "2"])
    try:
        pids = worker_pids(proc.pid)
        assert health(url) == (200, health(url)[1]) and health(url)[1]["status"] == "ok"
        os.kill(pids[0], signal.SIGKILL)
        t0 = time.monotonic()
        assert wait_for(lambda: health(url)[1]["workers_alive"] == 1, 2.0), health(url)
        seen = time.monotonic() - t0
        code, body = health(url)
        assert code == 200 and body["status"] == "degraded" and body["worker_deaths"] == 1
        assert seen < 1.0
        assert wait_for(lambda: health(url)[1]["status"] == "ok")  # replaced
        assert (
            metric(url, "planarloc_workers_alive") == 2
            and metric(url, "planarloc_worker_restarts_total") == 1
        )
        both = worker_pids(proc.pid)
        for pid in both:
            os.kill(pid, signal.SIGKILL)
        assert wait_for(lambda: health(url)[1]["workers_alive"] == 0, 1.5), health(url)
        code, body = health(url)
        assert code == 503 and body["status"] == "failing"
        assert metric(url, "planarloc_workers_alive") == 0
        assert wait_for(lambda: health(url)[1]["status"] == "ok")
        with Client(url) as client:
            assert client.localize(query_images(world)[0], camera)["name"]
    finally:
        stop_server(proc)


@pytest.fixture
def own_map(served_world, tmp_path) -> tuple[Path, Path, str, Path]:
    """A copy of the served map (to be broken), and a different map of the same world."""
    world, map_path, camera = served_world
    mine = tmp_path / "maps" / "office.db"
    mine.parent.mkdir()
    shutil.copy(map_path, mine)
    other = build_map(read_dataset(world / "map", "tum")[::2], tmp_path / "other.db", num_words=16)
    return world, mine, camera, other


def refused(url: str, image: Path, camera: str) -> tuple[int, str]:
    r = httpx.post(
        url + "/v1/localize",
        files={"image": (image.name, image.read_bytes())},
        data={"camera": camera},
        timeout=120,
    )
    return r.status_code, r.json().get("error", "")


@pytest.mark.parametrize("change", ["deleted", "replaced", "modified"])
def test_a_map_changed_under_the_server_is_refused_until_restart(own_map, change) -> None:
    world, mine, camera, other = own_map
    image = query_images(world)[0]
    url, proc = start_server(["--map", f"office={mine}", "--workers", "2"])
    try:
        with Client(url) as client:
            served = client.localize(image, camera, seed=1)
        assert served["success"]
        if change == "deleted":
            mine.unlink()
        elif change == "replaced":
            tmp = mine.with_name("incoming.db")
            shutil.copy(other, tmp)
            os.replace(tmp, mine)  # as a careful deploy script would do
        else:
            with open(mine, "r+b") as f:  # e.g. a `map build` appending to it
                f.seek(0, os.SEEK_END)
                f.write(b"\0" * 4096)
        code, body = health(url)
        assert code == 503 and body["status"] == "failing" and body["map_status"] == {"office": change}
        assert metric(url, 'planarloc_map_ok{map="office"}') == 0
        status, reason = refused(url, image, camera)
        assert status == 503 and change in reason and "restart" in reason and str(mine.parent) not in reason
        # A worker restarted now opens the new file: it must not answer from it either.
        for pid in worker_pids(proc.pid):
            os.kill(pid, signal.SIGKILL)
        assert wait_for(lambda: health(url)[1]["workers_alive"] == 2 or change == "deleted", 90)
        for _ in range(4):
            assert refused(url, image, camera)[0] == 503
    finally:
        stop_server(proc)


def test_a_worker_that_opened_another_version_is_never_used(own_map) -> None:
    """The file is replaced while the workers open it: the server's version and theirs differ."""
    world, mine, camera, other = own_map
    image = query_images(world)[0]
    url, proc = start_server(["--map", f"office={mine}", "--workers", "1"])
    try:
        shutil.copy(other, mine.with_name("new.db"))
        os.replace(mine.with_name("new.db"), mine)
        os.kill(worker_pids(proc.pid)[0], signal.SIGKILL)
        assert wait_for(lambda: health(url)[1]["map_status"]["office"] != "ok")
        assert refused(url, image, camera)[0] == 503
    finally:
        stop_server(proc)


def test_a_damaged_map_is_a_500_logged_without_paths(own_map) -> None:
    world, mine, camera, _other = own_map
    with sqlite3.connect(mine, isolation_level=None) as conn:  # every image's keypoint row cut short
        conn.execute("UPDATE keypoints SET data = substr(data, 1, 20)")
    conn.close()
    url, proc = start_server(["--map", f"office={mine}", "--workers", "1"])
    try:
        with Client(url, retries=0) as client:
            with pytest.raises(ServiceError) as exc:
                client.localize(query_images(world)[0], camera)
        assert exc.value.status == 500
        assert "damaged" in exc.value.reason and "map check" in exc.value.reason
        assert (
            str(mine) not in exc.value.reason
            and str(mine.parent) not in exc.value.reason
            and "/" not in exc.value.reason.replace("`planarloc map check`", "")
        )
        assert wait_for(
            lambda: any("keypoint" in line for line in proc.output.lines), 10
        )  # logged with details
        assert proc.poll() is None and health(url)[1]["status"] == "ok"  # the map file itself did not change
        assert metric(url, 'planarloc_rejected_total{reason="server_fault"}') == 1
    finally:
        stop_server(proc)
