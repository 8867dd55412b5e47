"""Helpers of the ROS 2 node's tests: a loopback-only ROS environment, and `planarloc ros2` as a
real subprocess whose output is collected."""

from __future__ import annotations

import contextlib
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path


def ros_env(domain: int) -> dict[str, str]:
    """Loopback-only discovery on its own domain, so parallel tests (and other users) never meet."""
    return {"ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}


@contextlib.contextmanager
def exclusive_domain() -> Iterator[int]:
    """A ROS domain (1..101) no other test on this machine holds: a lock file per domain in the
    temp folder, taken over when the process that made it is gone."""
    lock_dir = Path(tempfile.gettempdir()) / "planarloc-ros-domains"
    lock_dir.mkdir(exist_ok=True)
    for domain in random.Random(os.getpid() + time.monotonic_ns()).sample(range(1, 102), 101):
        lock = lock_dir / f"{domain}.lock"
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                os.kill(int(lock.read_text() or 0), 0)
                continue  # held by a live process
            except (ProcessLookupError, ValueError):
                lock.unlink(missing_ok=True)  # stale: its process is gone
                continue
            except PermissionError:
                continue
        os.write(fd, str(os.getpid()).encode())
        os.close(fd)
        try:
            yield domain
        finally:
            lock.unlink(missing_ok=True)
        return
    raise RuntimeError("every ROS domain 1..101 is held by a test")


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
