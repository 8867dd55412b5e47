"""A first use on an empty kernel cache (planarloc.compile.background and `planarloc localize --compile`):
the query answers as Python with the pose of the compiled kernels while one detached process compiles,
a second command joins that compile instead of starting another, the compile fills the cache and its lock
goes with it, and a bad ``PLANARLOC_COMPILE`` is one line."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from _cli_runs import cli, run
from map_files import map_build_argv

NOTICE = re.compile(
    r"planarloc's kernels are not compiled yet \((\d+) kernels\): (compiling them in the background|another "
    r"command is compiling them) \(pid (\d+), log (\S+)\); until it ends, queries run as Python, slower\. .*"
)


def _cold_env(tmp_path: Path) -> dict[str, str]:
    """An empty kernel cache and a temp folder of its own (the compile's lock and log): a fresh machine."""
    (tmp_path / "tmp").mkdir(exist_ok=True)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "TMPDIR": str(tmp_path / "tmp")}
    env.pop("PLANARLOC_COMPILE", None)
    return env


def _python(code: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=900)


def _lock_held(env: dict[str, str]) -> bool:
    code = "from planarloc.compile.background import _held, lock_path; print(_held(lock_path()))"
    proc = _python(code, env)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip() == "True"


def _pose(results: Path) -> np.ndarray:
    (line,) = results.read_text().splitlines()
    return np.array([float(x) for x in line.split()[1:]])


def test_a_cold_localize_answers_as_python_while_one_detached_process_compiles(
    tiny_world: Path, tmp_path: Path
) -> None:
    db = tmp_path / "m.db"
    assert run(map_build_argv(tiny_world / "map", db)) == 0
    query = sorted((tiny_world / "query" / "rgb").glob("*.png"))[1]
    cam = (tiny_world / "query" / "camera.txt").read_text().splitlines()[-1]
    argv = ["localize", "--map", db, query, "--camera", cam]
    assert run([*argv, "--out", tmp_path / "warm.txt"]) == 0  # the compiled kernels' answer

    env = _cold_env(tmp_path)
    first = cli(*argv, "--out", tmp_path / "cold.txt", "--compile", "background", env=env)
    assert first.returncode == 0, first.stderr
    notices = [m for m in map(NOTICE.fullmatch, first.stderr.splitlines()) if m]
    assert len(notices) == 1 and notices[0][2] == "compiling them in the background", first.stderr
    pid, log = int(notices[0][3]), Path(notices[0][4])
    try:
        np.testing.assert_allclose(_pose(tmp_path / "cold.txt"), _pose(tmp_path / "warm.txt"), atol=1e-6)
        assert log.is_relative_to(tmp_path / "tmp") and "compiling planarloc's kernels" in log.read_text()
        assert _lock_held(env)  # the compile outlives the command (a minute of CPU, not seconds)
        # auto with one query: the same; it joins the running compile instead of starting a second one
        second = cli(*argv, "--out", tmp_path / "cold2.txt", env=env)
        assert second.returncode == 0, second.stderr
        (joined,) = [m for m in map(NOTICE.fullmatch, second.stderr.splitlines()) if m]
        assert joined[2] == "another command is compiling them" and int(joined[3]) == pid
        np.testing.assert_allclose(_pose(tmp_path / "cold2.txt"), _pose(tmp_path / "warm.txt"), atol=1e-6)
    finally:
        os.killpg(pid, signal.SIGKILL)  # its own session: the compile and its workers
    deadline = time.monotonic() + 30
    while _lock_held(env) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not _lock_held(env)  # a killed compile leaves no lock behind


def test_the_background_compile_fills_the_cache_and_releases_its_lock(tmp_path: Path) -> None:
    env = _cold_env(tmp_path)
    start = (
        "from planarloc.compile.background import compile_in_background\n"
        "c = compile_in_background(['solvers'], jobs=2)\n"
        "again = compile_in_background(['solvers'], jobs=2)\n"
        "print(c.pid, c.ours, again.pid, again.ours, again.done())\n"
    )
    started = _python(start, env)
    assert started.returncode == 0, started.stderr
    pid, ours, pid2, ours2, done = started.stdout.split()
    assert (ours, ours2, done, pid2) == ("True", "False", "False", pid)  # one compile per cache
    deadline = time.monotonic() + 900
    while _lock_held(env):
        assert time.monotonic() < deadline, "the background compile did not end"
        time.sleep(0.5)
    check = (
        "from planarloc.compile import load_manifest, missing_kernels\n"
        "m = load_manifest()\n"
        "print(missing_kernels(m.for_steps(['solvers']), m))\n"
    )
    after = _python(check, env)
    assert after.returncode == 0 and after.stdout.strip() == "[]", after.stderr
    log = next((tmp_path / "tmp").rglob("*.log")).read_text()
    assert re.search(r"^compiled \d+ kernels in \d+\.\d s$", log, re.M), log


def test_a_bad_compile_setting_in_the_environment_is_one_line(tmp_path: Path) -> None:
    env = {**os.environ, "PLANARLOC_COMPILE": "later"}
    proc = cli("localize", "--map", tmp_path / "none.db", tmp_path / "q.png", env=env)
    assert proc.returncode == 1
    assert proc.stderr.strip() == (
        "planarloc localize: error: PLANARLOC_COMPILE='later': expected one of auto, background, wait "
        "(the default of --compile)"
    )


@pytest.mark.parametrize("value", ["wait", "background"])
def test_the_environment_sets_the_default_and_the_option_wins(value: str) -> None:
    from planarloc.cli.main import build_parser

    os.environ["PLANARLOC_COMPILE"] = value
    try:
        parser = build_parser()
        assert parser.parse_args(["localize", "--map", "m.db", "q.png"]).compile == value
        given = parser.parse_args(["localize", "--map", "m.db", "q.png", "--compile", "auto"])
        assert given.compile == "auto"
    finally:
        os.environ["PLANARLOC_COMPILE"] = "wait"  # the tests' setting (conftest)


def test_the_front_doors_setting_reads_the_environment_and_refuses_an_unknown_value(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from planarloc.compile.first_use import compile_setting

    monkeypatch.delenv("PLANARLOC_COMPILE")
    assert compile_setting() == "auto"
    monkeypatch.setenv("PLANARLOC_COMPILE", "wait")
    assert compile_setting() == "wait"
    monkeypatch.setenv("PLANARLOC_COMPILE", "soon")
    expected = r"^PLANARLOC_COMPILE='soon': expected one of auto, background, wait$"
    with pytest.raises(ValueError, match=expected):
        compile_setting()
