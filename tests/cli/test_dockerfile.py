"""The Dockerfile: a non-root USER after `planarloc warmup` ran as root, and its commands' equivalent run
here (no docker): the package installed read-only, warmed up as root, then queried as another user
without a HOME, loading every kernel from the install's cache."""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

from _cli_runs import cli
from map_files import map_build_argv
from other_user import base_env, other_user, run_as, shared_folder

REPO = Path(__file__).resolve().parents[2]


def instructions(text: str) -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` of a Dockerfile: comments dropped, continued lines joined."""
    out, pending = [], ""
    for line in text.splitlines():
        if not pending and (not line.strip() or line.lstrip().startswith("#")):
            continue
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        line, pending = pending + line, ""
        word, _, rest = line.strip().partition(" ")
        out.append((word.upper(), rest.strip()))
    return out


def _index(steps: list[tuple[str, str]], word: str, contains: str = "") -> int:
    found = [i for i, (w, rest) in enumerate(steps) if w == word and contains in rest]
    assert found, f"no {word} {contains!r} in the Dockerfile"
    return found[0]


def test_the_dockerfile_warms_up_as_root_then_runs_as_a_user_without_home() -> None:
    steps = instructions((REPO / "Dockerfile").read_text())
    assert steps[0][0] == "FROM" and steps[0][1].startswith("python:3.")
    pip, warmup = _index(steps, "RUN", "pip install ."), _index(steps, "RUN", "planarloc warmup")
    users = [i for i, (w, _) in enumerate(steps) if w == "USER"]
    assert users and pip < warmup < users[0], "warmup must run as root, after the install, before USER"
    user = steps[users[-1]][1]
    assert user not in ("root", "0") and not user.startswith(("root:", "0:"))
    useradd = steps[_index(steps, "RUN", "useradd")][1]
    assert f" {user}" in useradd and "--home-dir /nonexistent" in useradd and "--no-create-home" in useradd
    assert json.loads(steps[_index(steps, "ENTRYPOINT")][1]) == ["planarloc"]
    assert isinstance(json.loads(steps[_index(steps, "CMD")][1]), list)
    ignored = (REPO / ".dockerignore").read_text().split()
    assert "**/__pycache__" in ignored and ".venv" in ignored  # the image compiles its own kernels


def _pip_install(site: Path) -> None:
    """``RUN pip install .`` here: pip without network or build isolation when it can build the
    wheel offline, else the files setuptools installs (the package's modules and its package data)."""
    pip = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-index",
            "--no-build-isolation",
            "--target",
            str(site),
            str(REPO),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    if pip.returncode == 0:
        return
    data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    extra = {Path(*pkg.split(".")) / name for pkg, names in data.items() for name in names}
    for src in (REPO / "planarloc").rglob("*"):
        rel = src.relative_to(REPO)
        if src.is_file() and "__pycache__" not in rel.parts and (src.suffix == ".py" or rel in extra):
            (site / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(src, site / rel)


def test_the_dockerfile_commands_run_as_its_user(tiny_world: Path) -> None:
    user = other_user()  # the Dockerfile's `useradd ... --home-dir /nonexistent`
    with shared_folder() as root:
        site = root / "site"
        _pip_install(site)  # RUN pip install .  (as root: the user cannot write the install)
        assert (site / "planarloc" / "compile" / "kernels.json").is_file()
        # Seed numba's cache from this checkout's (same sources, so the same valid entries) to save
        # minutes of compiling on a shared machine; warmup below compiles whatever is not there.
        for f in (REPO / "planarloc").rglob("__pycache__/*.nb[ic]"):
            target = site / f.relative_to(REPO)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(f, target)
        env = base_env(PYTHONPATH=str(site))
        command = [sys.executable, "-m", "planarloc.cli.main"]
        # RUN, as root (cwd: `python -m` puts it first on sys.path, before PYTHONPATH)
        warm = cli("warmup", env=env, cwd=root, timeout=1800)
        assert warm.returncode == 0, warm.stderr
        assert re.match(r"warm-up done in", warm.stdout)
        shutil.copytree(tiny_world, root / "world")
        argv = map_build_argv(root / "world" / "map", root / "map.db", "--vocabulary-size", "16")
        built = cli(*argv, env=env, cwd=root, timeout=900)
        assert built.returncode == 0, built.stderr
        subprocess.run(["chmod", "-R", "a+rX", str(root)], check=True)
        work = root / "work"  # WORKDIR /work, the user's
        work.mkdir()
        os.chown(work, user.pw_uid, user.pw_gid)
        tmp = root / "tmp"
        tmp.mkdir(mode=0o1777)
        tmp.chmod(0o1777)
        as_user = base_env(PYTHONPATH=str(site), HOME="/nonexistent", TMPDIR=str(tmp))
        entry = [
            json.loads(v)
            for w, v in instructions((REPO / "Dockerfile").read_text())
            if w in ("ENTRYPOINT", "CMD")
        ]
        assert entry[0] == ["planarloc"]
        helped = run_as(user, [*command, *entry[1]], env=as_user, cwd=work)  # ENTRYPOINT + CMD
        assert helped.returncode == 0 and "usage: planarloc" in helped.stdout, helped.stderr
        query = sorted((root / "world" / "query" / "rgb").glob("*.png"))[0]
        cam = (root / "world" / "query" / "camera.txt").read_text().splitlines()[-1]
        proc = run_as(
            user,
            [*command, "localize", "--map", root / "map.db", query, "--camera", cam],
            env={**as_user, "NUMBA_DEBUG_CACHE": "1"},
            cwd=work,
        )
        assert proc.returncode == 0, proc.stderr
        assert len((work / "poses.txt").read_text().splitlines()) == 1
        loaded = [x for x in proc.stdout.splitlines() if "data loaded from" in x]
        assert loaded and all(shlex.split(x)[-1].startswith(str(site)) for x in loaded)  # the install's cache
        assert not [x for x in proc.stdout.splitlines() if "saved to" in x]  # nothing compiled and kept
        assert "for first use" not in proc.stderr and not list(tmp.iterdir())  # nor compiled: no user folder
