"""The ROS 2 node's fixtures: a map of the tiny world, a loopback-only ROS domain per test, and
`planarloc ros2` as a real subprocess."""

from __future__ import annotations

import itertools
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from planarloc.io.datasets import read_dataset
from planarloc.map.builder import build_map

_DOMAINS = itertools.count()


def ros_env(domain: int) -> dict[str, str]:
    """Loopback-only discovery on its own domain, so parallel tests (and other users) never meet."""
    return {"ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}


@pytest.fixture
def ros_domain(monkeypatch: pytest.MonkeyPatch) -> int:
    """A ROS domain of this test (1..100), set in this process's environment for rclpy."""
    domain = 1 + (os.getpid() * 13 + next(_DOMAINS) * 37) % 100
    for key, value in ros_env(domain).items():
        monkeypatch.setenv(key, value)
    return domain


@pytest.fixture(scope="session")
def world_map(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("ros2map") / "map.db"
    build_map(read_dataset(tiny_world / "map", "tum"), path)
    return path


def planarloc_command() -> list[str]:
    exe = Path(sys.executable).with_name("planarloc")
    return [str(exe)] if exe.exists() else [shutil.which("planarloc") or sys.executable, "-m", "planarloc.cli.main"]


class NodeProcess:
    """`planarloc ros2 ...` running in the background; its stderr is collected."""

    def __init__(self, args: list[str], env: dict[str, str]) -> None:
        self.proc = subprocess.Popen([*planarloc_command(), "ros2", *args], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, env={**os.environ, **env})
        self.stderr: list[str] = []
        self.stdout: list[str] = []
        self._threads = [threading.Thread(target=self._read, args=(s, out), daemon=True)
                         for s, out in ((self.proc.stderr, self.stderr), (self.proc.stdout, self.stdout))]
        for t in self._threads:
            t.start()

    def _read(self, stream, out: list[str]) -> None:
        for line in stream:
            out.append(line)

    def wait_ready(self, timeout: float = 240.0) -> None:
        end = time.monotonic() + timeout
        while not any("planarloc ros2: localizing" in line for line in self.stderr):
            if self.proc.poll() is not None:
                time.sleep(0.2)
                raise AssertionError(f"the node exited with {self.proc.returncode}: {''.join(self.stderr)}")
            if time.monotonic() > end:
                raise AssertionError(f"the node did not start within {timeout} s: {''.join(self.stderr)}")
            time.sleep(0.1)

    def interrupt(self, timeout: float = 60.0) -> int:
        self.proc.send_signal(signal.SIGINT)
        rc = self.proc.wait(timeout=timeout)
        for t in self._threads:
            t.join(timeout=5)
        return rc

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=30)


@pytest.fixture
def start_node(ros_domain: int) -> Iterator:
    started: list[NodeProcess] = []

    def start(*args: object) -> NodeProcess:
        node = NodeProcess([str(a) for a in args], ros_env(ros_domain))
        started.append(node)
        node.wait_ready()
        return node

    yield start
    for node in started:
        node.kill()
