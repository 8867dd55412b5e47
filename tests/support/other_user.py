"""Running commands as another local user (tests run as root): read-only installs, shared temp folders.

- :func:`other_user`: a non-root account for the tests (created with ``useradd`` if missing); the
  test is skipped, with the reason, when not run as root or without ``setpriv``.
- :func:`shared_folder`: a folder under the system temp folder that every user can enter (pytest's
  ``tmp_path`` is private to root), removed afterwards.
- :func:`run_as`: run a command as that user (``setpriv``). When the Python interpreter lives in a
  folder other users cannot enter (``/root/.pyenv``), the command runs in a private mount namespace
  (``unshare``) in which that folder is replaced by one that exposes only the interpreter's
  installation; ``read_only_tmp`` also makes the temp folders read-only there (nothing writable).
"""

from __future__ import annotations

import contextlib
import functools
import os
import pwd
import shlex
import shutil
import stat
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

USER = "planarloc-other"


def other_user() -> pwd.struct_passwd:
    """The test account (uid >= 1000 not required: a system account without HOME)."""
    if os.geteuid() != 0:
        pytest.skip("runs commands as another user: needs root (setpriv, useradd)")
    if shutil.which("setpriv") is None:
        pytest.skip("runs commands as another user: needs setpriv (util-linux)")
    try:
        return pwd.getpwnam(USER)
    except KeyError:
        if shutil.which("useradd") is None:
            pytest.skip(f"needs a user {USER!r} or useradd to create it")
        subprocess.run(
            [
                "useradd",
                "--system",
                "--no-create-home",
                "--home-dir",
                "/nonexistent",
                "--shell",
                "/usr/sbin/nologin",
                USER,
            ],
            check=True,
            capture_output=True,
        )
        return pwd.getpwnam(USER)


@contextlib.contextmanager
def shared_folder(prefix: str = "planarloc-test-") -> Iterator[Path]:
    """A fresh folder in the system temp folder (mode 0755: others may enter and read), removed after."""
    path = Path(tempfile.mkdtemp(prefix=prefix, dir="/tmp"))
    try:
        path.chmod(0o755)
        yield path
    finally:
        subprocess.run(["chmod", "-R", "u+w", str(path)], capture_output=True)
        shutil.rmtree(path, ignore_errors=True)


def _enterable_by_others(path: Path) -> Path | None:
    """The topmost folder on the way to ``path`` that other users cannot enter, or None."""
    here = Path("/")
    for part in Path(path).parts[1:]:
        here = here / part
        try:
            mode = os.stat(here).st_mode
        except OSError:
            return None
        if stat.S_ISDIR(mode) and not mode & stat.S_IXOTH:
            return here
    return None


def _interpreter_mounts(stage: Path) -> list[str]:
    """Shell lines that expose the interpreter's installation where its folder is closed to others."""
    needed = sorted(
        {Path(sys.base_prefix).resolve(), Path(os.path.realpath(sys.executable)).parent, Path(sys.prefix)}
    )
    lines, hidden = [], []
    for i, path in enumerate(needed):
        closed = _enterable_by_others(path)
        if closed is None:
            continue
        (stage / str(i)).mkdir(parents=True, exist_ok=True)
        lines.append(f"mount --bind {shlex.quote(str(path))} {shlex.quote(str(stage / str(i)))}")
        hidden.append((closed, path, stage / str(i)))
    for closed in sorted({c for c, _, _ in hidden}):
        lines.append(f"mount -t tmpfs -o mode=755 tmpfs {shlex.quote(str(closed))}")
    for _, path, staged in hidden:
        lines.append(
            f"mkdir -p {shlex.quote(str(path))} && mount --move {shlex.quote(str(staged))} "
            f"{shlex.quote(str(path))}"
        )
    return lines


@functools.cache
def _can_unshare() -> bool:
    if shutil.which("unshare") is None:
        return False
    return (
        subprocess.run(
            ["unshare", "--mount", "--propagation", "private", "true"], capture_output=True
        ).returncode
        == 0
    )


def run_as(
    user: pwd.struct_passwd,
    argv: Sequence[object],
    *,
    env: dict[str, str],
    cwd: Path | str = "/",
    read_only_tmp: bool = False,
    timeout: float = 900,
) -> subprocess.CompletedProcess:
    """Run ``argv`` as ``user`` with exactly ``env`` (add ``HOME`` to give one)."""
    argv = [str(a) for a in argv]
    drop = ["setpriv", f"--reuid={user.pw_uid}", f"--regid={user.pw_gid}", "--clear-groups", *argv]
    stage = Path(tempfile.mkdtemp(prefix="planarloc-test-stage-"))
    lines = _interpreter_mounts(stage)
    if read_only_tmp:
        for folder in ("/tmp", "/var/tmp"):
            if os.path.isdir(folder):
                lines.append(f"mount --bind {folder} {folder} && mount -o remount,bind,ro {folder}")
    if lines:
        if not _can_unshare():
            shutil.rmtree(stage, ignore_errors=True)
            pytest.skip(
                "needs a private mount namespace (unshare --mount): the interpreter is in a folder other "
                "users cannot enter, or read_only_tmp was asked for"
            )
        script = " && ".join([*lines, 'exec "$@"'])
        drop = ["unshare", "--mount", "--propagation", "private", "sh", "-c", script, "sh", *drop]
    try:
        return subprocess.run(drop, env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def base_env(**extra: str) -> dict[str, str]:
    """A minimal environment for :func:`run_as`: PATH, locale and PYTHONPATH to the planarloc under test
    (no HOME, no TMPDIR, no NUMBA_*)."""
    import planarloc

    env = {
        "PATH": os.environ.get("PATH", "/usr/bin:/bin"),
        "LANG": "C.UTF-8",
        "PYTHONPATH": str(Path(planarloc.__file__).resolve().parents[1]),
    }
    env.update(extra)
    return env
