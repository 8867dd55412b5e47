"""`planarloc cache list|clean`: where the caches are, what they hold, and cleaning them safely: this
user's own folders, never a symbolic link or another user's folder followed."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _cli_runs import cli
from other_user import base_env, other_user, run_as, shared_folder

from planarloc.features.extract import Features
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.map.posed_image import PosedImage
from planarloc.map.store import MapDatabase


def _small_map(path: Path) -> None:
    rng = np.random.default_rng(0)
    with MapDatabase.create(path, {"features": "test"}) as db:
        d = rng.random((20, 128), dtype=np.float32)
        db.add_image(
            PosedImage(
                "a.png", Path("a.png"), Pose.identity(), Camera("PINHOLE", 64, 48, (50, 50, 32, 24)), 0
            ),
            Features(
                rng.random((20, 2), dtype=np.float32) * 40,
                d / np.linalg.norm(d, axis=1, keepdims=True),
                np.ones(20, np.float32),
            ),
        )


@pytest.fixture
def env(tmp_path: Path) -> dict:
    """A temp folder and a numba cache of this test's own (the real ones are left alone)."""
    (tmp_path / "tmp").mkdir()
    return {**os.environ, "TMPDIR": str(tmp_path / "tmp"), "NUMBA_CACHE_DIR": str(tmp_path / "numba")}


def test_list_says_where_and_clean_removes_maps_and_bags_but_not_a_map_being_built(
    env: dict, tmp_path: Path
) -> None:
    mine = tmp_path / "tmp" / f"planarloc-{os.geteuid()}"
    maps, bags = mine / "maps", mine / "bags"
    for name in ("kitti_seq2-every4-0123.db", "busy.db"):
        _small_map(maps / name)
    (bags / "run1-abc" / "image").mkdir(parents=True)
    (bags / "run1-abc" / "image" / "000001.png").write_bytes(b"x" * 5000)
    listing = cli("cache", "list", env=env)
    assert listing.returncode == 0, listing.stderr
    lines = {line.split()[0]: line for line in listing.stdout.splitlines()}
    assert f"{maps}: " in lines["maps"] and "evaluate" in lines["maps"]
    assert f"{bags}: 1 files, 5 KB" in lines["bags"]
    assert str(tmp_path / "numba") in lines["kernels"] and "planarloc warmup" in lines["kernels"]

    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from planarloc.map.lock import MapWriterLock; "
            f"l = MapWriterLock({str(maps / 'busy.db')!r}); l.acquire(); print('held', flush=True); "
            "sys.stdin.read()",
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        cleaned = cli("cache", "clean", env=env)
    finally:
        holder.communicate("", timeout=60)
    assert cleaned.returncode == 0, cleaned.stderr
    assert (
        "maps" in cleaned.stdout
        and "removed 1 maps" in cleaned.stdout
        and "removed 1 files, 5 KB" in cleaned.stdout
    )
    assert f"kept {maps / 'busy.db'}: a map build holds it" in cleaned.stderr
    assert sorted(p.name for p in maps.glob("*.db")) == ["busy.db"] and not list(bags.rglob("*.png"))


def test_clean_kernels_removes_the_compiled_kernels_only(env: dict, tmp_path: Path) -> None:
    compile_one = (
        "import numpy as np; from planarloc.robust.sampling import _pick_weighted; "
        "_pick_weighted(0.5, np.ones(3), -1)"
    )
    subprocess.run([sys.executable, "-c", compile_one], env=env, check=True, timeout=600)
    cached = sorted((tmp_path / "numba").rglob("*.nb[ic]"))
    assert cached and all(p.name.startswith("sampling.") for p in cached)
    (tmp_path / "numba" / "keep.txt").write_text("not a kernel")
    kernels = [
        line for line in cli("cache", "list", env=env).stdout.splitlines() if line.startswith("kernels")
    ]
    assert str(cached[0].parent) in kernels[0] and f": {len(cached)} files" in kernels[0]
    out = cli("cache", "clean", "kernels", env=env)
    assert out.returncode == 0 and f"removed {len(cached)} files" in out.stdout
    assert not list((tmp_path / "numba").rglob("*.nb[ic]")) and (tmp_path / "numba" / "keep.txt").exists()


def test_unknown_cache_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from planarloc.cli.main import main

    assert main(["cache", "clean", "pictures"]) == 1
    assert capsys.readouterr().err.strip() == (
        "planarloc cache: error: unknown cache 'pictures': expected maps, bags, kernels or all"
    )


def test_cache_folders_are_this_users_and_closed_to_others(env: dict, tmp_path: Path) -> None:
    code = "from planarloc.map.settings import cache_dir; print(cache_dir('maps'))"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    folder = Path(out.stdout.strip())
    assert folder == tmp_path / "tmp" / f"planarloc-{os.geteuid()}" / "maps"
    for level in (folder, folder.parent):
        assert level.stat().st_mode & 0o777 == 0o700 and level.stat().st_uid == os.geteuid()


def _roots_files(root: Path) -> Path:
    """A folder of root's with files and a subfolder: what a planted link aims at."""
    target = root / "roots-data"
    (target / "sub").mkdir(parents=True)
    (target / "precious.txt").write_text("keep me")
    (target / "sub" / "more.png").write_bytes(b"x" * 100)
    return target


def _intact(target: Path) -> bool:
    return (target / "precious.txt").read_text() == "keep me" and (target / "sub" / "more.png").is_file()


def test_a_link_planted_by_another_user_never_makes_cache_clean_delete_roots_files() -> None:
    """Another local user plants, in the shared temp folder, the old fixed names (planarloc-bags,
    planarloc-maps) and this user's own folder name (planarloc-<uid>) as links to a folder of root's:
    root's `cache clean` deletes nothing there; the planted folder name is refused in one line."""
    user = other_user()
    with shared_folder() as shared:
        target = _roots_files(shared)
        tmp = shared / "tmp"
        tmp.mkdir(mode=0o1777)
        tmp.chmod(0o1777)
        plant = base_env()
        for name in ("planarloc-bags", "planarloc-maps"):
            made = run_as(user, ["ln", "-s", target, tmp / name], env=plant)
            assert made.returncode == 0, made.stderr
        # `clean all` also cleans the kernels: aimed at a folder of this test, never the checkout's
        env = {**os.environ, "TMPDIR": str(tmp), "NUMBA_CACHE_DIR": str(shared / "numba")}
        cleaned = cli("cache", "clean", "all", env=env)
        assert cleaned.returncode == 0, cleaned.stderr
        assert _intact(target)
        made = run_as(user, ["ln", "-s", target, tmp / f"planarloc-{os.geteuid()}"], env=plant)
        assert made.returncode == 0, made.stderr
        for argv in (["cache", "clean"], ["cache", "list"]):
            refused = cli(*argv, env=env)
            assert refused.returncode == 1 and _intact(target)
            err = refused.stderr.strip().splitlines()
            assert len(err) == 1 and f"planarloc-{os.geteuid()} is a symbolic link" in err[0], refused.stderr
        os.unlink(tmp / f"planarloc-{os.geteuid()}")
        made = run_as(user, ["mkdir", "-m", "0777", tmp / f"planarloc-{os.geteuid()}"], env=plant)  # theirs
        assert made.returncode == 0, made.stderr
        refused = cli("cache", "clean", env=env)
        assert refused.returncode == 1 and f"belongs to {user.pw_name}" in refused.stderr
        made_map = subprocess.run(
            [sys.executable, "-c", "from planarloc.map.settings import cache_dir; cache_dir('maps')"],
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert made_map.returncode != 0 and "belongs to" in made_map.stderr  # evaluate's maps never go there


def test_clean_removes_a_link_inside_its_folders_not_its_target(env: dict, tmp_path: Path) -> None:
    target = _roots_files(tmp_path)
    bags = tmp_path / "tmp" / f"planarloc-{os.geteuid()}" / "bags"
    (bags / "run1-abc" / "image").mkdir(parents=True)
    (bags / "run1-abc" / "image" / "000001.png").write_bytes(b"x" * 5000)
    (bags / "run1-abc" / "linked").symlink_to(target)  # a folder link inside the cache
    (bags / "run1-abc" / "file-link.png").symlink_to(target / "precious.txt")
    listing = cli("cache", "list", env=env)
    assert "bags" in listing.stdout and ": 3 files, 5 KB" in listing.stdout  # links count as links, 0 bytes
    cleaned = cli("cache", "clean", "bags", env=env)
    assert cleaned.returncode == 0, cleaned.stderr
    assert _intact(target) and not list(bags.iterdir())
