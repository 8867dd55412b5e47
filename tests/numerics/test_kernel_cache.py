"""numba's kernel cache on a read-only install (planarloc.numerics.kernel_cache): another user loads the
kernels compiled at build time without compiling, with or without a HOME; a kernel the install lacks
goes to that user's temp folder, or stays in memory where nothing is writable, said in one line."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from fresh_python import python_stdout
from map_files import SMALL_VOCABULARY, map_build_argv
from other_user import base_env, other_user, run_as, shared_folder

import planarloc

PACKAGE = Path(planarloc.__file__).parent
#: Runs the CLI (or one kernel call, ``--kernel``) in-process and reports on stderr, as ``PROBE {json}``,
#: what numba compiled (its ``numba:compile`` events) and how many kernels came from its cache.
PROBE = """
import json, logging, sys
from numba.core import event
compiled = []
class Recorder(event.Listener):
    def on_start(self, ev):
        d = ev.data["dispatcher"]
        compiled.append(f"{d.py_func.__module__}:{d.py_func.__qualname__}")
    def on_end(self, ev):
        pass
event.register("numba:compile", Recorder())
import planarloc
if sys.argv[1] == "--kernel":  # a signature no warm-up compiles
    import numpy as np
    from planarloc.geometry import mat3
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    mat3.dot(np.ones(3, np.int16), np.ones(3, np.int16))
    rc = 0
else:
    from planarloc.cli.main import main
    rc = main(sys.argv[1:])
from planarloc.compile.dispatchers import planarloc_dispatchers
hits = sum(sum(d.stats.cache_hits.values()) for d in planarloc_dispatchers().values())
print("PROBE " + json.dumps({"file": planarloc.__file__, "rc": rc, "compiled": compiled, "hits": hits}),
      file=sys.stderr)
"""


@dataclass
class Install:
    root: Path
    site: Path
    probe: Path
    localize: list[str]
    user: object


def _report(proc: subprocess.CompletedProcess) -> dict:
    lines = [x for x in proc.stderr.splitlines() if x.startswith("PROBE ")]
    assert proc.returncode == 0 and lines, f"exit {proc.returncode}; stderr:\n{proc.stderr[-3000:]}"
    return json.loads(lines[-1][len("PROBE ") :])


def _files(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def _cache_lines(proc: subprocess.CompletedProcess) -> list[str]:
    return [x for x in proc.stderr.splitlines() if "planarloc.numerics.kernel_cache" in x]


def _sticky(folder: Path) -> Path:
    """A temp folder like /tmp: everyone may create files, only in their own names."""
    folder.mkdir()
    folder.chmod(0o1777)
    return folder


@pytest.fixture(scope="module")
def install(tiny_world: Path):
    """This package copied with its warm kernel cache into a folder other users can read, a map of
    the tiny world built as root; the kernels the localize run needs warmed as root (the image
    build), then the copy made read-only."""
    user = other_user()
    with shared_folder() as root:
        site = root / "site"
        shutil.copytree(PACKAGE, site / "planarloc", ignore=shutil.ignore_patterns("*.pyc", "*.tmp.*"))
        world = root / "world"
        shutil.copytree(tiny_world, world)
        probe = root / "probe.py"
        probe.write_text(PROBE)
        env = base_env(PYTHONPATH=str(site))
        built = subprocess.run(
            [
                sys.executable,
                "-m",
                "planarloc.cli.main",
                *map_build_argv(world / "map", root / "map.db", *SMALL_VOCABULARY),
            ],
            env=env,
            capture_output=True,
            text=True,
            timeout=900,
            cwd=root,
        )
        assert built.returncode == 0, built.stderr
        query = sorted((world / "query" / "rgb").glob("*.png"))[0]
        cam = (world / "query" / "camera.txt").read_text().splitlines()[-1]
        localize = ["localize", "--map", str(root / "map.db"), str(query), "--camera", cam, "--out", "-"]
        warm = subprocess.run(
            [sys.executable, probe, *localize], env=env, capture_output=True, text=True, timeout=900
        )
        assert _report(warm)["file"] == str(site / "planarloc" / "__init__.py")  # the copy, not the checkout
        subprocess.run(["chmod", "-R", "a-w", str(site)], check=True)
        subprocess.run(["chmod", "-R", "a+rX", str(root)], check=True)
        yield Install(root, site, probe, localize, user)


@pytest.mark.parametrize("home", ["no HOME", "a writable HOME"])
def test_localize_as_another_user_loads_the_read_only_warm_cache_and_compiles_nothing(
    install: Install, home: str
) -> None:
    tmp = _sticky(install.root / f"tmp-{home.replace(' ', '-')}")
    env = base_env(PYTHONPATH=str(install.site), TMPDIR=str(tmp))
    if home != "no HOME":
        env["HOME"] = str(install.root / "home")
        (install.root / "home").mkdir()
        os.chown(install.root / "home", install.user.pw_uid, install.user.pw_gid)
    before = _files(install.site)
    proc = run_as(install.user, [sys.executable, install.probe, *install.localize], env=env)
    report = _report(proc)
    assert report["rc"] == 0 and report["file"] == str(install.site / "planarloc" / "__init__.py")
    assert report["compiled"] == [] and report["hits"] > 20  # every kernel loaded from the install's cache
    assert len([x for x in proc.stdout.splitlines() if len(x.split()) == 8]) == 1  # the pose
    assert "for first use" not in proc.stderr and not _cache_lines(proc)
    assert _files(install.site) == before and not list(tmp.iterdir())  # nothing written anywhere
    if home != "no HOME":
        assert not list((install.root / "home").iterdir())  # no ~/.cache/numba: the warm cache was enough


def test_a_kernel_the_install_lacks_is_kept_in_the_users_temp_folder(install: Install) -> None:
    tmp = _sticky(install.root / "tmp-missing-kernel")
    env = base_env(PYTHONPATH=str(install.site), TMPDIR=str(tmp))
    first = run_as(install.user, [sys.executable, install.probe, "--kernel"], env=env)
    assert "planarloc.geometry.mat3:dot" in _report(first)["compiled"]
    folder = tmp / f"planarloc-{install.user.pw_uid}"
    lines = _cache_lines(first)
    assert (
        len(lines) == 1 and lines[0].startswith("WARNING") and f"cached in {folder / 'kernels'}" in lines[0]
    )
    st = folder.stat()
    assert st.st_uid == install.user.pw_uid and st.st_mode & 0o777 == 0o700
    assert list((folder / "kernels").rglob("mat3.dot-*.nbi"))
    second = run_as(install.user, [sys.executable, install.probe, "--kernel"], env=env)
    assert _report(second)["compiled"] == [] and not _cache_lines(second)  # loaded from there


def test_where_nothing_is_writable_kernels_compile_in_memory_said_in_one_line(install: Install) -> None:
    env = base_env(PYTHONPATH=str(install.site))  # no HOME, the temp folders read-only, cwd /
    proc = run_as(install.user, [sys.executable, install.probe, "--kernel"], env=env, read_only_tmp=True)
    assert "planarloc.geometry.mat3:dot" in _report(proc)["compiled"]
    lines = _cache_lines(proc)
    assert len(lines) == 1 and "stay in memory" in lines[0] and "NUMBA_CACHE_DIR" in lines[0], proc.stderr


def test_a_temp_folder_of_that_name_made_by_someone_else_is_never_used(install: Install) -> None:
    tmp = _sticky(install.root / "tmp-planted")
    planted = tmp / f"planarloc-{install.user.pw_uid}"
    (planted / "kernels").mkdir(parents=True)  # root's, 0755: made first by another user
    env = base_env(PYTHONPATH=str(install.site), TMPDIR=str(tmp))
    proc = run_as(install.user, [sys.executable, install.probe, "--kernel"], env=env)
    assert "planarloc.geometry.mat3:dot" in _report(proc)["compiled"]
    lines = _cache_lines(proc)
    assert len(lines) == 1 and "stay in memory" in lines[0] and f"{planted} belongs to root" in lines[0]
    assert not list((planted / "kernels").iterdir())


def test_every_kernel_is_defined_after_the_cache_class_is_in_place() -> None:
    code = (
        "import planarloc.cli.main, planarloc.localize.localizer\n"
        "from planarloc.compile.dispatchers import planarloc_dispatchers\n"
        "from planarloc.numerics.kernel_cache import KernelCache\n"
        "ds = planarloc_dispatchers()\n"
        "print(len(ds), sorted(k for k, d in ds.items() if type(d._cache) is not KernelCache))\n"
    )
    count, others = python_stdout(code, timeout=600).split(" ", 1)
    assert int(count) > 50 and others.strip() == "[]"


# ---- a stale or damaged index (another planarloc version, an edited checkout) -------------------------
KERNEL_CALL = (
    "import numpy as np\n"
    "from planarloc.geometry.so3 import exp_so3\n"
    "print(repr(float(exp_so3(np.array([0.1, 0.2, 0.3])).sum())))\n"
)


def _call_kernel(cache_dir: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}
    return subprocess.run(
        [sys.executable, "-c", KERNEL_CALL], env=env, capture_output=True, text=True, timeout=600
    )


def _index_of(cache_dir: Path) -> Path:
    (index,) = cache_dir.rglob("so3.exp_so3-*.nbi")
    return index


def _read_index(index: Path) -> tuple[object, bytes]:
    import pickle

    with open(index, "rb") as f:
        version = pickle.load(f)
        return version, f.read()


def _poison_with_a_removed_type(index: Path) -> None:
    """Rewrite the index as another version of the module would have left it: an entry naming a type
    (``planarloc.geometry.so3.RemovedType``) that this version does not have."""
    import pickle

    from planarloc.geometry import so3

    version, payload = _read_index(index)
    stamp, overloads = pickle.loads(payload)
    removed = type("RemovedType", (), {"__module__": so3.__name__})
    so3.RemovedType = removed  # reachable while pickled, then gone
    try:
        data = pickle.dumps((stamp, {**overloads, ("stale",): removed}))
    finally:
        del so3.RemovedType
    with open(index, "wb") as f:
        pickle.dump(version, f)
        f.write(data)


def _truncate(index: Path) -> None:
    version, payload = _read_index(index)
    import pickle

    with open(index, "wb") as f:
        pickle.dump(version, f)
        f.write(payload[: len(payload) // 2])


def _truncate_data(index: Path) -> None:
    """The kernel's data file (``*.nbc``) cut in half; its index intact."""
    (data,) = index.parent.glob(index.name.replace(".nbi", ".*.nbc"))
    data.write_bytes(data.read_bytes()[: data.stat().st_size // 2])


@pytest.mark.parametrize(
    "damage",
    [_poison_with_a_removed_type, _truncate, _truncate_data],
    ids=["removed type", "truncated index", "truncated data"],
)
def test_a_cache_file_that_cannot_be_unpickled_is_a_cache_miss(tmp_path: Path, damage) -> None:
    import pickle

    first = _call_kernel(tmp_path)
    assert first.returncode == 0, first.stderr
    index = _index_of(tmp_path)
    damage(index)
    again = _call_kernel(tmp_path)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout == first.stdout  # compiled again, the same kernel
    stamp, overloads = pickle.loads(_read_index(index)[1])  # written anew, without the stale entry
    assert len(overloads) == 1 and ("stale",) not in overloads
