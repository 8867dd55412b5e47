"""Start a `planarloc serve` subprocess on a free loopback port (for scripts, tests and benchmarks);
find its worker processes and their memory."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from collections import deque
from pathlib import Path

from planarloc.extras import require

#: The banner ``planarloc serve`` prints on stderr once its socket is bound.
BANNER = re.compile(r"^serving .* on http://(?P<host>[^\s]+):(?P<port>\d+) ")


class ServerOutput:
    """The output of a server process, read by a thread (the pipe never fills up); the last lines kept."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.lines: deque[str] = deque(maxlen=200)
        self.port: int | None = None
        self.bound = threading.Event()
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen) -> None:
        for raw in proc.stdout:  # type: ignore[union-attr]
            line = raw.decode("utf-8", "replace").rstrip("\n")
            self.lines.append(line)
            m = BANNER.match(line)
            if m and self.port is None:
                self.port = int(m.group("port"))
                self.bound.set()
        self.bound.set()

    def text(self) -> str:
        return "\n".join(self.lines)


def start_server(
    args: list[str], timeout_s: float = 600.0, env: dict[str, str] | None = None
) -> tuple[str, subprocess.Popen]:
    """Run ``planarloc serve ARGS --host 127.0.0.1 --port 0`` and wait until ``/healthz`` answers.

    ``timeout_s`` defaults to the workers' own start-up limit (``worker_pool.STARTUP_TIMEOUT_S``,
    not imported: this module stays light): on an empty kernel cache with ``PLANARLOC_COMPILE=wait``
    they compile before the banner. A server that exits is seen at once.

    The server binds any free port and names it in its banner, so two servers never race for one.
    ``env``: variables added to the server's environment (e.g. ``PLANARLOC_TOKEN``, ``TMPDIR``).

    Returns:
        the base URL and the process (stop it with :func:`stop_server`; its output is
        ``proc.output``, a :class:`ServerOutput`).

    Raises:
        RuntimeError: the server exited or did not answer within ``timeout_s`` (its output attached).
    """
    httpx = require("httpx", "serve")
    root = str(Path(__file__).resolve().parents[2])
    env = {
        **os.environ,
        **(env or {}),
        "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])),
    }
    proc = subprocess.Popen(
        [sys.executable, "-m", "planarloc.cli.main", "serve", *args, "--host", "127.0.0.1", "--port", "0"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    output = ServerOutput(proc)
    proc.output = output  # type: ignore[attr-defined]
    deadline = time.monotonic() + timeout_s
    output.bound.wait(timeout_s)
    if output.port is None:
        stop_server(proc)
        raise RuntimeError(f"planarloc serve did not start: {output.text()[-2000:]}")
    url = f"http://127.0.0.1:{output.port}"
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"planarloc serve exited: {output.text()[-2000:]}")
        try:
            if httpx.get(url + "/healthz", timeout=1.0).status_code == 200:
                return url, proc
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    stop_server(proc)
    raise RuntimeError(f"planarloc serve did not answer on {url} within {timeout_s:.0f} s")


def stop_server(proc: subprocess.Popen) -> None:
    """SIGTERM, then SIGKILL after 10 s."""
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)


def worker_pids(server_pid: int) -> list[int]:
    """Process ids of a server's localization workers (Linux ``/proc``: children running spawn_main)."""
    pids = set()
    for children in Path(f"/proc/{server_pid}/task").glob("*/children"):
        for pid in children.read_text().split():
            try:
                if b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes():
                    pids.add(int(pid))
            except FileNotFoundError:
                continue
    return sorted(pids)


def rss_bytes(pids: list[int]) -> int:
    """Total resident memory of processes (Linux ``/proc/PID/status`` VmRSS)."""
    total = 0
    for pid in pids:
        try:
            for line in Path(f"/proc/{pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) * 1024
        except FileNotFoundError:
            continue
    return total
