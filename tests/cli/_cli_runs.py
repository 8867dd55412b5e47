"""Running `planarloc` in the command-line tests: in this process (:func:`run`) or in a new one
(:func:`cli`), and the argument lists several tests share (a map build's is ``map_files.map_build_argv``): an
evaluation of one that maps every 2nd image, a localization against a map."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable, Mapping
from pathlib import Path

from planarloc.cli.main import main


def run(argv: list) -> int:
    """`planarloc ARGV` in this process (paths and numbers passed as strings): its exit code."""
    return main([str(a) for a in argv])


def cli(
    *argv: object,
    env: Mapping[str, str] | None = None,
    cwd: Path | None = None,
    preexec: Callable[[], None] | None = None,
    timeout: float = 600,
) -> subprocess.CompletedProcess:
    """`planarloc ARGV` in a new process, stdout and stderr captured as text (without ``env``, this
    process's environment: PYTHONPATH is inherited, so this checkout's package)."""
    return subprocess.run(
        [sys.executable, "-m", "planarloc.cli.main", *map(str, argv)],
        capture_output=True,
        text=True,
        env=env,
        cwd=cwd,
        preexec_fn=preexec,
        timeout=timeout,
    )


def evaluate_argv(data: Path, tmp_path: Path, *options: object) -> list:
    """`evaluate DATA --format tum --map-every 2 --map TMP_PATH/e.db OPTIONS`."""
    return ["evaluate", data, "--format", "tum", "--map-every", "2", "--map", tmp_path / "e.db", *options]


def kitti_evaluate_argv(sequence: Path, db: Path, *options: object) -> list:
    """`evaluate SEQUENCE -f kitti --map-every 2 --map DB --structure tracks OPTIONS`."""
    protocol = ("--map-every", "2", "--map", db, "--structure", "tracks")
    return ["evaluate", sequence, "-f", "kitti", *protocol, *options]


def localize_argv(db: Path, *args: object) -> list:
    """`localize --map DB ARGS`."""
    return ["localize", "--map", db, *args]
