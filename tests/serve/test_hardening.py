"""Hostile clients against a real server on loopback: bodies over the limit in every transfer
encoding (raw sockets, chunked), slow clients (slowloris: headers and bodies trickled byte by byte),
bounded queue and job times, hostile values in every form field, and the token kept out of the
process list."""

from __future__ import annotations

import os
import signal
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from served import Served, serving

from planarloc.cli.main import main
from planarloc.client import Client, ServiceError, resolve_token
from planarloc.serve.launcher import start_server, stop_server, worker_pids

BOUNDARY = "planarloc-test-boundary"
TOKEN = "hardening-token"


@pytest.fixture(scope="module")
def strict(served_world, tmp_path_factory) -> Iterator[Served]:
    """A server with short limits, its temporary folder a private empty one, the token from a file."""
    tmp = tmp_path_factory.mktemp("server-tmp")
    token_file = tmp_path_factory.mktemp("secret") / "token"
    token_file.write_text(TOKEN + "\n")
    limits = ["--workers", "2", "--queue", "2", "--max-image-mb", "1"]
    timeouts = ["--body-timeout", "3", "--header-timeout", "2"]  # s
    options = [*limits, *timeouts, "--token-file", str(token_file)]
    with serving(served_world, options, TOKEN, env={"TMPDIR": str(tmp)}) as served:
        served.process.tmpdir = tmp  # type: ignore[attr-defined]
        yield served


def port_of(server: Served) -> int:
    return int(server.url.rsplit(":", 1)[1])


def multipart(fields: dict[str, str], image: bytes | None, filename: str = "q.png") -> bytes:
    parts = []
    for k, v in fields.items():
        parts.append(f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n{v}\r\n'.encode())
    if image is not None:
        parts.append(
            f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="image"; filename="{filename}"\r\n'
            "Content-Type: image/png\r\n\r\n".encode()
            + image
            + b"\r\n"
        )
    return b"".join(parts) + f"--{BOUNDARY}--\r\n".encode()


def head(server: Served, extra: str = "", token: str | None = TOKEN) -> bytes:
    auth = f"Authorization: Bearer {token}\r\n" if token else ""
    return (
        f"POST /v1/localize HTTP/1.1\r\nHost: 127.0.0.1\r\n{auth}"
        f"Content-Type: multipart/form-data; boundary={BOUNDARY}\r\n{extra}\r\n"
    ).encode()


def read_response(sock: socket.socket, timeout: float = 60) -> tuple[int, bytes]:
    """Status code and raw bytes of an HTTP response (until the server closes or the body is complete)."""
    sock.settimeout(timeout)
    data = b""
    while True:
        try:
            chunk = sock.recv(65536)
        except (ConnectionResetError, BrokenPipeError):
            break
        if not chunk:
            break
        data += chunk
        if b"\r\n\r\n" in data:
            header, _, body = data.partition(b"\r\n\r\n")
            for line in header.split(b"\r\n"):
                if line.lower().startswith(b"content-length:") and len(body) >= int(line.split(b":")[1]):
                    return int(data.split(b" ", 2)[1]), data
    return (int(data.split(b" ", 2)[1]) if data.startswith(b"HTTP/") else -1), data


def chunked(data: bytes, size: int = 65536) -> Iterator[bytes]:
    for i in range(0, len(data), size):
        piece = data[i : i + size]
        yield f"{len(piece):x}\r\n".encode() + piece + b"\r\n"
    yield b"0\r\n\r\n"


def dir_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def png_of(server: Served, i: int = 0) -> bytes:
    return sorted((server.world / "query" / "rgb").glob("*.png"))[i].read_bytes()


# ---- upload limits, every transfer encoding ----------------------------------------------------------
def test_a_chunked_body_is_cut_off_at_the_limit_and_nothing_is_spooled(strict) -> None:
    """102 MB announced by nobody (chunked, no Content-Length): refused once the limit (1 MB + 64 KB)
    is passed, while it streams; the server's temporary folder never receives a byte."""
    body = multipart({"camera": strict.camera}, b"\0" * (102 * 2**20))
    sent = 0
    peak = 0
    with socket.create_connection(("127.0.0.1", port_of(strict))) as sock:
        sock.sendall(head(strict, "Transfer-Encoding: chunked\r\n"))
        try:
            for piece in chunked(body):
                sock.sendall(piece)
                sent += len(piece)
                peak = max(peak, dir_bytes(strict.process.tmpdir))
        except (BrokenPipeError, ConnectionResetError):
            pass
        status, raw = read_response(sock)
    assert status == 413, raw[:300]
    assert b"over the limit" in raw and b"Connection: close" in raw.replace(b"connection", b"Connection")
    assert sent < 20 * 2**20  # cut off long before the end
    assert peak == 0 and dir_bytes(strict.process.tmpdir) == 0


def test_content_length_over_the_limit_is_refused_before_the_body(strict) -> None:
    with socket.create_connection(("127.0.0.1", port_of(strict))) as sock:
        sock.sendall(head(strict, f"Content-Length: {200 * 2**20}\r\n"))  # no body sent at all
        status, raw = read_response(sock, timeout=10)
    assert status == 413 and b"over the limit" in raw
    with socket.create_connection(("127.0.0.1", port_of(strict))) as sock:  # a lie: more bytes than declared
        body = multipart({"camera": strict.camera}, png_of(strict))
        sock.sendall(head(strict, "Content-Length: 100\r\n") + body)
        status, _ = read_response(sock, timeout=10)
    assert 400 <= status < 500


def test_a_valid_chunked_upload_is_served(strict) -> None:
    body = multipart({"camera": strict.camera, "seed": "1"}, png_of(strict))
    with socket.create_connection(("127.0.0.1", port_of(strict))) as sock:
        sock.sendall(head(strict, "Transfer-Encoding: chunked\r\n") + b"".join(chunked(body, 1000)))
        status, raw = read_response(sock)
    assert status == 200 and b'"status"' in raw


def test_per_part_limits(strict) -> None:
    auth = {"Authorization": f"Bearer {TOKEN}"}
    url = strict.url + "/v1/localize"
    cases = [
        ({"camera": strict.camera + " " * (20 * 1024)}, 413),  # a text field over 16 KB
        ({"camera": strict.camera, "gravity": "0 1 0"}, 200),
    ]
    for fields, status in cases:
        r = httpx.post(
            url, headers=auth, files={"image": ("q.png", png_of(strict))}, data=fields, timeout=120
        )
        assert r.status_code == status, r.text
    twice = multipart({"camera": strict.camera, "seed": "1"}, png_of(strict)).replace(
        b'name="seed"', b'name="camera"'
    )
    r = httpx.post(
        url,
        headers={**auth, "Content-Type": f"multipart/form-data; boundary={BOUNDARY}"},
        content=twice,
        timeout=60,
    )
    assert r.status_code == 400 and "given twice" in r.json()["error"]


# ---- slow clients --------------------------------------------------------------------------------------
def trickle(server: Served, stop: threading.Event, what: str, results: list) -> None:
    """A slowloris client: headers (or a body) one byte per 0.5 s until the server closes it."""
    body = multipart({"camera": server.camera}, png_of(server))
    with socket.create_connection(("127.0.0.1", port_of(server))) as sock:
        t0 = time.monotonic()
        if what == "body":
            sock.sendall(head(server, f"Content-Length: {len(body)}\r\n") + body[:10])
            rest = body[10:]
        else:
            rest = head(server, f"Content-Length: {len(body)}\r\n")
        try:
            for b in rest:
                if stop.is_set():
                    break
                sock.sendall(bytes([b]))
                time.sleep(0.5)
        except (BrokenPipeError, ConnectionResetError):
            pass
        status, _ = read_response(sock, timeout=30)
        results.append((what, status, time.monotonic() - t0))


def test_slow_clients_cannot_lock_others_out(strict) -> None:
    """Six body trickers and six header trickers at once (capacity is 4): they hold no admission
    place, everyone else is served meanwhile, and each slow client is cut off after its timeout
    (408 for a body after 3 s, the connection closed for headers after 2 s)."""
    stop = threading.Event()
    results: list = []
    kinds = ["body"] * 6 + ["head"] * 6
    slow = [threading.Thread(target=trickle, args=(strict, stop, what, results)) for what in kinds]
    for t in slow:
        t.start()
    try:
        time.sleep(1.0)
        health = httpx.get(strict.url + "/healthz").json()
        assert health["admitted"] == 0  # trickling bodies hold no place
        with Client(strict.url, token=TOKEN, retries=0) as client:
            for i in range(2):
                t0 = time.monotonic()
                assert client.localize(png_of(strict, i), strict.camera, seed=1)["name"]
                assert time.monotonic() - t0 < 60
        for t in slow:
            t.join(30)
    finally:
        stop.set()
    assert len(results) == 12
    bodies = [r for r in results if r[0] == "body"]
    heads = [r for r in results if r[0] == "head"]
    assert all(status == 408 and 2.5 < took < 15 for _, status, took in bodies), bodies
    assert all(status == -1 and 1.5 < took < 15 for _, status, took in heads), heads  # closed, no answer


def test_waiting_and_running_are_bounded(served_world) -> None:
    """Frozen worker: the running request is answered 503 when its job time is up (its worker
    replaced), the queued one 503 when its queue time is up; then the pool serves again."""
    world, map_path, camera = served_world
    url, proc = start_server(
        [
            "--map",
            str(map_path),
            "--workers",
            "1",
            "--queue",
            "1",
            "--queue-timeout",
            "2",
            "--job-timeout",
            "5",
        ]
    )
    try:
        image = sorted((world / "query" / "rgb").glob("*.png"))[0]
        before = worker_pids(proc.pid)
        os.kill(before[0], signal.SIGSTOP)
        results: dict[str, tuple[int, str, float]] = {}

        def one(key: str) -> None:
            t0 = time.monotonic()
            r = httpx.post(
                url + "/v1/localize",
                files={"image": (image.name, image.read_bytes())},
                data={"camera": camera},
                timeout=60,
            )
            results[key] = (r.status_code, r.json()["error"], time.monotonic() - t0)

        first = threading.Thread(target=one, args=("running",))
        first.start()
        deadline = time.monotonic() + 20
        while httpx.get(url + "/healthz").json()["busy"] < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        second = threading.Thread(target=one, args=("queued",))
        second.start()
        first.join(60)
        second.join(60)
        assert (
            results["queued"][0] == 503 and "within 2 s" in results["queued"][1] and results["queued"][2] < 4
        )
        assert results["running"][0] == 503 and "longer than 5 s" in results["running"][1]
        deadline = time.monotonic() + 60
        while httpx.get(url + "/healthz").json()["status"] != "ok" and time.monotonic() < deadline:
            time.sleep(0.2)
        assert worker_pids(proc.pid) != before
        with Client(url) as client:
            assert client.localize(image, camera)["name"] == image.name
    finally:
        stop_server(proc)


# ---- hostile field values: always a one-line 4xx -------------------------------------------------------
HOSTILE = [
    "9" * 400,
    "-" + "9" * 400,
    "1e400",
    "1e308",
    "nan",
    "inf",
    "-inf",
    "1e-400",
    "0x10",
    "²",
    "١٢",
    "\x00",
    "😀",
    " ",
    "1_000",
    "+5",
    "0",
    "-0",
    "1" * 5000,
    "\u202e",
    "%00",
    "'; DROP TABLE images; --",
]


def test_hostile_field_values_are_4xx_never_5xx(strict) -> None:
    auth = {"Authorization": f"Bearer {TOKEN}"}
    url = strict.url + "/v1/localize"
    cam = strict.camera.split()
    forms = []
    for v in HOSTILE:
        for i in range(1, len(cam)):
            forms.append({"camera": " ".join([*cam[:i], v, *cam[i + 1 :]])})
        forms.append({"camera": " ".join([v, *cam[1:]])})
        forms.append({"camera": strict.camera, "gravity": f"0 {v} 0"})
        forms.append({"camera": strict.camera, "gravity": f"{v} {v} {v}"})
        for name in ("seed", "method", "structure", "map", "session", "stamp", "odometry"):
            forms.append({"camera": strict.camera, name: v})
        forms.append({"camera": strict.camera, "session": "r1", "stamp": v})
        forms.append({"camera": strict.camera, "session": "r1", "stamp": "1", "odometry": f"0 0 0 0 0 0 {v}"})
    statuses: dict[int, int] = {}
    with httpx.Client(headers=auth, timeout=120) as http:
        for fields in forms:
            r = http.post(url, files={"image": ("q.png", png_of(strict))}, data=fields)
            statuses[r.status_code] = statuses.get(r.status_code, 0) + 1
            assert r.status_code < 500, (fields, r.text)
            if r.status_code != 200:
                reason = r.json()["error"]
                assert reason and "\n" not in reason and str(strict.map_path.parent) not in reason
        for name in ("q\x00.png", "q\n.png", "a" * 300 + ".png", "😀.png"):
            r = http.post(url, files={"image": (name, png_of(strict))}, data={"camera": strict.camera})
            assert r.status_code in (200, 400), (name, r.text)
    assert statuses.get(400, 0) > len(forms) // 2
    assert strict.process.poll() is None


# ---- the token: from a file or the environment, never in the process list --------------------------------
def test_the_token_comes_from_a_file_or_the_environment(strict, served_world, tmp_path, monkeypatch) -> None:
    assert TOKEN.encode() not in Path(f"/proc/{strict.process.pid}/cmdline").read_bytes()
    image = png_of(strict)
    r = httpx.post(
        strict.url + "/v1/localize", files={"image": ("q.png", image)}, data={"camera": strict.camera}
    )
    assert r.status_code == 401
    with Client(strict.url, token=TOKEN) as client:
        assert client.localize(image, strict.camera, name="q.png")["name"] == "q.png"
    _world, map_path, camera = served_world
    url, proc = start_server(["--map", str(map_path), "--workers", "1"], env={"PLANARLOC_TOKEN": "from-env"})
    try:
        assert b"from-env" not in Path(f"/proc/{proc.pid}/cmdline").read_bytes()
        assert httpx.get(url + "/v1/maps").status_code == 401
        assert httpx.get(url + "/v1/maps", headers={"Authorization": "Bearer from-env"}).status_code == 200
        # `localize --server` reads the same sources.
        monkeypatch.setenv("PLANARLOC_TOKEN", "from-env")
        query = sorted((strict.world / "query" / "rgb").glob("*.png"))[0]
        localize = ["localize", "--server", url, "--map", map_path.stem, str(query), "--camera", camera]
        assert main([*localize, "--out", str(tmp_path / "p.txt")]) == 0
        token_file = tmp_path / "t"
        token_file.write_text("wrong\n")
        assert main([*localize, "--token-file", str(token_file), "--out", str(tmp_path / "q.txt")]) == 1
    finally:
        stop_server(proc)
    for bad, match in [
        ((None, tmp_path / "missing"), "cannot read"),
        (("a", tmp_path / "t"), "give one"),
        (("a b", None), "printable ASCII"),
    ]:
        with pytest.raises(ValueError, match=match):
            resolve_token(*bad)
    (tmp_path / "empty").write_text("\n")
    with pytest.raises(ValueError, match="empty"):
        resolve_token(None, tmp_path / "empty")
    with pytest.raises(ServiceError):
        with Client(url, token=TOKEN, retries=0) as client:
            client.maps()
