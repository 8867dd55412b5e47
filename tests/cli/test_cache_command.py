"""`planarloc cache list|clean`: where the caches are, what they hold, and cleaning them safely."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from planarloc.features.extract import Features
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.map.posed_image import PosedImage
from planarloc.map.store import MapDatabase


def cli(*args: object, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "planarloc.cli.main", *map(str, args)], capture_output=True,
                          text=True, env=env, timeout=600)


def _small_map(path: Path) -> None:
    rng = np.random.default_rng(0)
    with MapDatabase.create(path, {"features": "test"}) as db:
        d = rng.random((20, 128), dtype=np.float32)
        db.add_image(PosedImage("a.png", Path("a.png"), Pose.identity(), Camera("PINHOLE", 64, 48, (50, 50, 32, 24)), 0),
                     Features(rng.random((20, 2), dtype=np.float32) * 40, d / np.linalg.norm(d, axis=1, keepdims=True),
                              np.ones(20, np.float32)))


@pytest.fixture
def env(tmp_path: Path) -> dict:
    """A temp folder and a numba cache of this test's own (the real ones are left alone)."""
    (tmp_path / "tmp").mkdir()
    return {**os.environ, "TMPDIR": str(tmp_path / "tmp"), "NUMBA_CACHE_DIR": str(tmp_path / "numba")}


def test_list_says_where_and_clean_removes_maps_and_bags_but_not_a_map_being_built(env: dict, tmp_path: Path) -> None:
    maps, bags = tmp_path / "tmp" / "planarloc-maps", tmp_path / "tmp" / "planarloc-bags"
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

    holder = subprocess.Popen([sys.executable, "-c", "import sys; from planarloc.map.lock import MapWriterLock; "
                               f"l = MapWriterLock({str(maps / 'busy.db')!r}); l.acquire(); print('held', flush=True); "
                               "sys.stdin.read()"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert holder.stdout.readline().strip() == "held"
        cleaned = cli("cache", "clean", env=env)
    finally:
        holder.communicate("", timeout=60)
    assert cleaned.returncode == 0, cleaned.stderr
    assert "maps" in cleaned.stdout and "removed 1 maps" in cleaned.stdout and "removed 1 files, 5 KB" in cleaned.stdout
    assert f"kept {maps / 'busy.db'}: a map build holds it" in cleaned.stderr
    assert sorted(p.name for p in maps.glob("*.db")) == ["busy.db"] and not list(bags.rglob("*.png"))


def test_clean_kernels_removes_the_compiled_kernels_only(env: dict, tmp_path: Path) -> None:
    compile_one = ("import numpy as np; from planarloc.robust.sampling import _pick_weighted; "
                   "_pick_weighted(0.5, np.ones(3), -1)")
    subprocess.run([sys.executable, "-c", compile_one], env=env, check=True, timeout=600)
    cached = sorted((tmp_path / "numba").rglob("*.nb[ic]"))
    assert cached and all(p.name.startswith("sampling.") for p in cached)
    (tmp_path / "numba" / "keep.txt").write_text("not a kernel")
    kernels = [line for line in cli("cache", "list", env=env).stdout.splitlines() if line.startswith("kernels")]
    assert str(cached[0].parent) in kernels[0] and f": {len(cached)} files" in kernels[0]
    out = cli("cache", "clean", "kernels", env=env)
    assert out.returncode == 0 and f"removed {len(cached)} files" in out.stdout
    assert not list((tmp_path / "numba").rglob("*.nb[ic]")) and (tmp_path / "numba" / "keep.txt").exists()


def test_unknown_cache_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from planarloc.cli.main import main

    assert main(["cache", "clean", "pictures"]) == 1
    assert capsys.readouterr().err.strip() == ("planarloc cache: error: unknown cache 'pictures': expected maps, "
                                               "bags, kernels or all")
