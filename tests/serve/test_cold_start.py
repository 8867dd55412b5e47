"""`planarloc serve` on an empty kernel cache: the workers share one detached compile and answer as
Python meanwhile, with the poses of the compiled kernels."""

from __future__ import annotations

import json
import math
import os
import re
import signal
import time
from pathlib import Path

import httpx
import numpy as np
from served import serving

from planarloc.cli.main import main
from planarloc.client import Client

# The worker that joins may read the compile's lock before its starter has written the pid there:
# it then says "pid not yet known" (both name the compile's log).
NOTICE = re.compile(
    r".*kernels are not compiled yet .*: "
    r"(compiling them in the background|another command is compiling them) "
    r"\(pid (\d+|not yet known), log (\S+)\)"
)


def test_a_cold_service_compiles_once_for_its_workers_and_answers_as_python(
    served_world, tmp_path: Path
) -> None:
    world, map_path, camera = served_world
    image = sorted((world / "query" / "rgb").glob("*.png"))[0]
    (tmp_path / "tmp").mkdir()
    cold = {
        "NUMBA_CACHE_DIR": str(tmp_path / "numba"),  # empty: a machine without the warm-up
        "TMPDIR": str(tmp_path / "tmp"),
        "PLANARLOC_COMPILE": "auto",  # the default (the tests' conftest sets wait)
    }
    pids: set[int] = set()
    try:
        with serving(served_world, ["--workers", "2", "--queue", "2"], env=cold) as served:
            notices = [m for m in map(NOTICE.match, served.process.output.text().splitlines()) if m]
            pids = {int(m[2]) for m in notices if m[2].isdigit()}
            # One notice per worker, one compile between them: one started it, the other joined it.
            assert len(notices) == 2 and len({m[3] for m in notices}) == 1, served.process.output.text()
            assert len(pids) == 1, served.process.output.text()  # the starter always knows it
            assert sorted(m[1] for m in notices) == [
                "another command is compiling them",
                "compiling them in the background",
            ]
            # The server says that its workers answer as Python, and stops once the compile ends.
            assert as_python(served.url) == (2, 2.0)
            with Client(served.url) as client:
                record = client.localize(image, camera, map="office", structure="tracks", seed=7)
            assert as_python(served.url) == (2, 2.0)  # the compile takes minutes: it still runs
            for pid in pids:
                os.killpg(pid, signal.SIGKILL)  # ended (here killed): the lock is released
            deadline = time.monotonic() + 30
            while as_python(served.url) != (0, 0.0) and time.monotonic() < deadline:
                time.sleep(0.1)
            assert as_python(served.url) == (0, 0.0)
            assert httpx.get(served.url + "/healthz").json()["status"] == "ok"
    finally:
        for pid in pids:
            try:
                os.killpg(pid, signal.SIGKILL)  # the detached compile and its workers (minutes of CPU)
            except ProcessLookupError:
                pass
    out = tmp_path / "poses.txt"  # the same query with this process' compiled kernels
    args = ["localize", "--map", str(map_path), str(image), "--camera", camera, "--structure", "tracks"]
    assert main([*args, "--seed", "7", "--out", str(out)]) == 0
    local = json.loads((tmp_path / "poses.txt.json.d" / (image.name + ".json")).read_text())
    assert record["success"] and record["status"] == local["status"]
    for key in "num_inliers num_inliers_3d model".split():
        assert record[key] == local[key], key
    for key in "quat_wxyz t position_std_m".split():
        np.testing.assert_allclose(record[key], local[key], rtol=1e-9, atol=1e-12, err_msg=key)


def as_python(url: str) -> tuple[int, float]:
    """Workers that run as Python, by ``/healthz`` and by ``/metrics``."""
    health = httpx.get(url + "/healthz", timeout=10).json()["workers_as_python"]
    lines = httpx.get(url + "/metrics", timeout=10).text.splitlines()
    gauge = [float(line.split()[1]) for line in lines if line.startswith("planarloc_workers_as_python ")]
    return health, gauge[0] if len(gauge) == 1 else math.nan


def test_a_bad_compile_setting_stops_the_server_in_one_line(served_world) -> None:
    import subprocess
    import sys

    _world, map_path, _camera = served_world
    proc = subprocess.run(
        [sys.executable, "-m", "planarloc.cli.main", "serve", "--map", str(map_path), "--port", "0"],
        env={**os.environ, "PLANARLOC_COMPILE": "later"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode != 0 and len(lines) == 1, proc.stderr
    assert "PLANARLOC_COMPILE='later'" in lines[0]
