"""The real server on a loopback port, spoken to over HTTP (httpx)."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from record_schemas import check

from planarloc.cli.main import main
from planarloc.client import Client, ServiceError
from planarloc.serve.launcher import worker_pids


def queries(server, n: int = 3) -> list[Path]:
    return sorted((server.world / "query" / "rgb").glob("*.png"))[:n]


def test_served_pose_equals_cli_pose(server, tmp_path: Path) -> None:
    images = queries(server)
    out = tmp_path / "poses.txt"
    common = [*map(str, images), "--structure", "tracks", "--seed", "7"]
    camera = ["--camera", server.camera]
    assert main(["localize", "--map", str(server.map_path), *common, *camera, "--out", str(out)]) == 0
    with Client(server.url, token=server.token) as client:
        for image in images:
            local = json.loads((tmp_path / "poses.txt.json.d" / (image.name + ".json")).read_text())
            served = client.localize(image, server.camera, map="office", structure="tracks", seed=7)
            check("record", served, "served record")
            check("record", local, "localize record")
            assert served["success"] and served["status"] == local["status"]
            # Same RANSAC run: equal counters and models; floats equal up to summation order (worker
            # processes may align arrays differently, which moves the last bit of numpy's sums).
            for key in "name num_inliers num_inliers_3d num_matches references model".split():
                assert served[key] == local[key], key
            for key in "quat_wxyz t position_std_m".split():
                np.testing.assert_allclose(served[key], local[key], rtol=1e-9, atol=1e-12, err_msg=key)
            assert served["stats"] == local["stats"]  # same RANSAC run: same counters
    # localize --server writes the same files as the local run (camera: the served map's only one).
    remote = tmp_path / "remote.txt"
    server_args = ["--server", server.url, "--token", server.token, "--map", "second"]
    assert main(["localize", *server_args, *common, "--out", str(remote)]) == 0
    assert same_words_and_numbers(remote.read_text(), out.read_text())
    for path in sorted((tmp_path / "remote.txt.json.d").glob("*.json")):  # localize --server's records too
        check("record", path.read_text(), str(path))


def same_words_and_numbers(a: str, b: str) -> bool:
    """Two results files hold the same words and the same numbers up to the last bits."""
    words_a, words_b = a.split(), b.split()
    if len(words_a) != len(words_b):
        return False
    for wa, wb in zip(words_a, words_b):
        if wa == wb:
            continue
        try:
            fa, fb = float(wa), float(wb)
        except ValueError:
            return False
        if abs(fa - fb) > 1e-12 + 1e-9 * abs(fb):
            return False
    return True


def test_malformed_requests_get_one_line_4xx_and_the_server_stays_up(server) -> None:
    image = queries(server, 1)[0]
    png = image.read_bytes()
    cam = server.camera
    auth = {"Authorization": f"Bearer {server.token}"}
    url = server.url + "/v1/localize"

    def form(data: bytes | None = png, **fields: str | None) -> dict:
        """A localize form with the valid defaults, where a None field is left out."""
        fields = {k: v for k, v in {"camera": cam, "map": "office", **fields}.items() if v is not None}
        return {"files": {"image": ("q.png", data)}, "data": fields} if data is not None else {"data": fields}

    battery = [
        ("not an image", form(b"GIF89a...."), 415),
        ("truncated png", form(png[:40]), 400),
        ("too large", form(png + b"\0" * (2 << 20)), 413),
        ("camera garbage", form(camera="hello"), 400),
        ("camera model", form(camera="FISHEYE 320 240 1 2 3"), 400),
        ("camera size", form(camera="PINHOLE 640 480 500 500 320 240"), 400),
        ("no image", form(None), 400),
        ("image as text", form(None, image="abc"), 400),
        ("no map of two", form(map=None), 400),
        ("unknown map", form(map="nope"), 404),
        ("map as path", form(map=str(server.map_path)), 404),
        ("traversal", form(map="../office"), 404),
        ("bad gravity", form(gravity="0 1"), 400),
        ("bad method", form(method="9p"), 400),
        ("bad seed", form(seed="-3"), 400),
        ("unknown field", form(x="1"), 400),
        ("json body", {"json": {"camera": cam}}, 415),
    ]
    with httpx.Client(headers=auth, timeout=60) as http:
        for what, kwargs, status in battery:
            r = http.post(url, **kwargs)
            assert r.status_code == status, (what, r.text)
            reason = check("service-error", r.text, what)["error"]
            assert reason and "\n" not in reason, what
        r = http.post(
            url, content=b"--x\r\nbroken", headers={"content-type": "multipart/form-data; boundary=x"}
        )
        assert 400 <= r.status_code < 500
        assert http.get(server.url + "/v1/maps").json()["maps"][0]["name"] == "office"
        assert str(server.map_path) not in http.get(server.url + "/v1/maps").text
    unauth = httpx.post(url, files={"image": ("q.png", png)}, data={"camera": cam, "map": "office"})
    assert unauth.status_code == 401 and unauth.headers["www-authenticate"] == "Bearer"
    assert server.process.poll() is None
    health = httpx.get(server.url + "/healthz").json()
    assert health["status"] == "ok" and health["workers_as_python"] == 0  # a warm kernel cache
    with Client(server.url, token=server.token) as client:
        given = client.localize(image, cam, map="office", seed=3)
        assert given["name"] == image.name
        # Without a camera the map's only camera is used, as by `planarloc localize`.
        default = client.localize(image, None, map="office", seed=3)
        assert (
            default["success"] and default["quat_wxyz"] == given["quat_wxyz"] and default["t"] == given["t"]
        )
        with pytest.raises(ServiceError) as exc:
            client.localize(b"not an image", cam, map="office")
        assert exc.value.status == 415
        with pytest.raises(ServiceError) as exc:  # decodes as nothing: refused by the worker, not a 500
            client.localize(png[:2000], cam, map="office")
        assert exc.value.status == 400 and "cannot decode" in exc.value.reason


def test_overload_answers_503_with_retry_after_and_nothing_else(server) -> None:
    import os
    import signal

    image = queries(server, 1)[0]
    capacity, extra = 2 + 2, 3  # 2 workers + queue 2 (conftest), and 3 requests more
    statuses: list[tuple[int, str | None]] = []

    def one() -> None:
        with httpx.Client(timeout=120, headers={"Authorization": f"Bearer {server.token}"}) as http:
            r = http.post(
                server.url + "/v1/localize",
                files={"image": (image.name, image.read_bytes())},
                data={"camera": server.camera, "map": "office", "structure": "tracks"},
            )
            statuses.append((r.status_code, r.headers.get("retry-after")))

    # Frozen workers finish nothing: the first `capacity` requests stay admitted, so every
    # request beyond them must be refused at once with a 503 (not queued, not failed otherwise).
    pids = worker_pids(server.process.pid)
    for pid in pids:
        os.kill(pid, signal.SIGSTOP)
    threads = [threading.Thread(target=one) for _ in range(capacity + extra)]
    try:
        for t in threads:
            t.start()
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(statuses) < extra:
            time.sleep(0.05)
        assert sorted(statuses) == [(503, statuses[0][1])] * extra, statuses
        assert httpx.get(server.url + "/healthz").json()["admitted"] == capacity
    finally:
        for pid in pids:
            os.kill(pid, signal.SIGCONT)
    for t in threads:
        t.join(180)
    codes = [s for s, _ in statuses]
    assert sorted(codes) == [200] * capacity + [503] * extra, codes
    assert all(ra and int(ra) >= 1 for s, ra in statuses if s == 503)
    metrics = httpx.get(server.url + "/metrics", headers={"Authorization": f"Bearer {server.token}"}).text
    assert 'planarloc_requests_total{code="200",endpoint="/v1/localize"}' in metrics
    assert 'planarloc_requests_total{code="503",endpoint="/v1/localize"}' in metrics
    assert 'planarloc_rejected_total{reason="overloaded"} 3.0' in metrics
    assert (
        "planarloc_request_seconds_bucket" in metrics
        and 'planarloc_localize_total{status="success"}' in metrics
    )


def test_worker_killed_mid_request_fails_cleanly_and_the_pool_recovers(server) -> None:
    import os
    import signal

    image = queries(server, 1)[0]
    pids = worker_pids(server.process.pid)
    assert len(pids) == 2
    result: dict = {}

    def one() -> None:
        with Client(server.url, token=server.token, retries=0) as client:
            try:
                result["record"] = client.localize(image, server.camera, map="office", structure="tracks")
            except ServiceError as exc:
                result["error"] = exc

    # Freeze the workers first, so that the request is still in flight when they die: a fast
    # estimate could otherwise finish between "admitted" and the kill.
    for pid in pids:
        os.kill(pid, signal.SIGSTOP)
    t = threading.Thread(target=one)
    t.start()
    # Kill only once the request is admitted (handed to a worker): under load the upload
    # and parsing alone can take longer than any fixed sleep.
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and httpx.get(server.url + "/healthz").json()["admitted"] < 1:
        time.sleep(0.01)
    for pid in pids:  # whichever holds the request
        os.kill(pid, signal.SIGKILL)
    t.join(60)
    assert "error" in result and result["error"].status == 503 and "died" in result["error"].reason
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and httpx.get(server.url + "/healthz").json()["workers_alive"] < 2:
        time.sleep(0.2)
    health = httpx.get(server.url + "/healthz").json()
    assert health["status"] == "ok" and health["worker_restarts"] >= 1
    assert set(worker_pids(server.process.pid)).isdisjoint(pids)
    with Client(server.url, token=server.token) as client:
        assert client.localize(image, server.camera, map="office", structure="tracks")["success"]


def test_workers_never_outlive_a_killed_server(served_world) -> None:
    import os
    import signal

    from planarloc.serve.launcher import start_server

    _world, map_path, _camera = served_world
    _url, proc = start_server(["--map", str(map_path), "--workers", "1"])
    workers = worker_pids(proc.pid)
    assert len(workers) == 1
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(10)

    def running(pid: int) -> bool:  # a zombie (exited, not yet reaped by init) is not running
        try:
            return "\tZ" not in Path(f"/proc/{pid}/status").read_text().split("State:")[1].split("\n")[0]
        except (FileNotFoundError, IndexError):
            return False

    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and any(running(pid) for pid in workers):
        time.sleep(0.2)
    assert not any(running(pid) for pid in workers)


def test_port_0_prints_the_bound_port_and_a_busy_port_is_one_line(server, served_world) -> None:
    import socket
    import subprocess
    import sys

    banner = next(line for line in server.process.output.lines if line.startswith("serving "))
    port = int(server.url.rsplit(":", 1)[1])
    assert port != 0 and f"on http://127.0.0.1:{port} (2 workers, queue 2)" in banner  # started with --port 0
    assert httpx.get(f"http://127.0.0.1:{port}/healthz").status_code == 200
    _world, map_path, _camera = served_world
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = busy.getsockname()[1]
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "planarloc.cli.main",
                "serve",
                "--map",
                str(map_path),
                "--port",
                str(taken),
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.splitlines() == [
        f"planarloc serve: error: --port {taken}: 127.0.0.1:{taken} is already in "
        "use (another server?); choose another port, or --port 0 for any free one"
    ]


def test_localize_server_records_an_undecodable_image_and_goes_on(server, tmp_path: Path) -> None:
    images = queries(server, 2)
    broken = tmp_path / "broken.png"
    broken.write_bytes(images[0].read_bytes()[:3000])  # a PNG header, then nothing: undecodable
    out = tmp_path / "poses.txt"
    args = [
        "localize",
        "--server",
        server.url,
        "--token",
        server.token,
        "--map",
        "office",
        images[0],
        broken,
        images[1],
        "--structure",
        "tracks",
        "--out",
        out,
    ]
    assert main([str(a) for a in args]) == 3
    records = {
        r["name"]: r for r in (json.loads(p.read_text()) for p in (tmp_path / "poses.txt.json.d").iterdir())
    }
    assert records["broken.png"]["status"] == "error" and "cannot decode" in records["broken.png"]["message"]
    assert sorted(line.split()[0] for line in out.read_text().splitlines()) == sorted(p.name for p in images)
    # A server that cannot be reached stops the run (exit 1) and leaves the results file as it was.
    before = out.read_text()
    dead = ["localize", "--server", "http://127.0.0.1:9", "--map", "office", images[0], "--out", out]
    assert main([str(a) for a in dead]) == 1 and out.read_text() == before


def test_a_failed_query_answers_strict_json(server) -> None:
    """A black frame fails (no features): its answer has no pose and no finite std, and says so
    with nulls a strict parser accepts, not NaN or Infinity (issue 32)."""
    import cv2

    w, h = (int(v) for v in server.camera.split()[1:3])
    ok, png = cv2.imencode(".png", np.zeros((h, w), np.uint8))
    assert ok
    response = httpx.post(
        server.url + "/v1/localize",
        headers={"Authorization": f"Bearer {server.token}"},
        files={"image": ("black.png", png.tobytes())},
        data={"camera": server.camera, "map": "office"},
        timeout=120,
    )
    body = check("record", response.text, "answer to a black frame")
    assert response.status_code == 200 and body["success"] is False
    assert "position_std_m" in body and body["position_std_m"] is None
