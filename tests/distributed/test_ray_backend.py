"""Map building, evaluation and the Ray Serve deployment on a small local Ray instance (2 CPUs)."""

from __future__ import annotations

import json
import socket
from pathlib import Path

import numpy as np
import pytest

ray = pytest.importorskip("ray", reason="the ray extra is not installed (pip install 'planarloc[ray]')")

from planarloc.cli.main import main  # noqa: E402
from planarloc.distributed.ray_backend import RayBackend, check_address  # noqa: E402
from planarloc.evaluation.queries import evaluate_queries, split_map_queries  # noqa: E402
from planarloc.io.datasets import read_dataset  # noqa: E402
from planarloc.localize.localizer import Localizer, LocalizerConfig  # noqa: E402
from planarloc.map.builder import build_map  # noqa: E402
from planarloc.map.store import MapDatabase  # noqa: E402
from planarloc.robust.options import RansacOptions  # noqa: E402
from planarloc.synthetic.world.export import generate  # noqa: E402
from planarloc.synthetic.world.presets import get_preset, shrunk  # noqa: E402


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    config = shrunk(get_preset("office"), scale=0.5, n_map=12, n_query=4)
    return generate(config, tmp_path_factory.mktemp("world") / "office", seed=0)


def assert_same_map_content(a_path: Path, b_path: Path) -> None:
    with MapDatabase.open(a_path, mode="r") as a, MapDatabase.open(b_path, mode="r") as b:
        pa, pb = {p.name: p for p in a.posed_images()}, {p.name: p for p in b.posed_images()}
        assert list(pa) == list(pb) and len(pa) > 0
        for name in pa:
            assert np.array_equal(pa[name].cam_from_world.matrix4, pb[name].cam_from_world.matrix4)
            fa, fb = a.get_features(name), b.get_features(name)
            assert np.array_equal(fa.keypoints, fb.keypoints) and np.array_equal(
                fa.descriptors, fb.descriptors
            )
        (ia, ga), (ib, gb) = a.get_global_descriptors(), b.get_global_descriptors()
        assert np.array_equal(ia, ib) and np.array_equal(ga, gb)
        assert a.get_blob("retrieval/vlad_vocabulary") == b.get_blob("retrieval/vlad_vocabulary")
        assert a.is_complete and b.is_complete


def test_addresses_are_checked() -> None:
    assert check_address(None) is None and check_address("local") is None
    assert check_address("auto") == "auto" and check_address("127.0.0.1:6379") == "127.0.0.1:6379"
    assert check_address("ray://127.0.0.1:10001") == "ray://127.0.0.1:10001"
    with pytest.raises(ValueError, match="not a Ray address"):
        check_address("data/kitti_seq2")


def check_map_build_on_ray_equals_local_build(world: Path, tmp_path: Path, backend: RayBackend) -> None:
    local = build_map(read_dataset(world / "map", "tum"), tmp_path / "local.db")
    # The CLI reuses the Ray instance this process is connected to (the fixture's local one).
    assert (
        main(["map", "build", str(world / "map"), "-f", "tum", "--out", str(tmp_path / "ray.db"), "--ray"])
        == 0
    )
    assert_same_map_content(local, tmp_path / "ray.db")
    # The ordered map yields task results in input order and re-raises a task's error.
    assert list(backend.map(abs, [-3, 1, -2, 5, -8], window=2)) == [3, 1, 2, 5, 8]
    with pytest.raises(Exception, match="math domain"):
        list(backend.map(np.math.sqrt if hasattr(np, "math") else __import__("math").sqrt, [4.0, -1.0]))


def check_evaluate_on_ray_equals_local(world: Path, tmp_path: Path) -> None:
    images = read_dataset(world / "map", "tum")
    map_images, queries = split_map_queries(images, 2)
    db = build_map(map_images, tmp_path / "e.db")
    config = LocalizerConfig(ransac=RansacOptions(structure="tracks", seed=3))
    local = evaluate_queries(Localizer(db, config), queries)
    assert sum(r.success for r in local) >= len(local) // 2
    summary = tmp_path / "eval.json"
    assert (
        main(
            [
                "evaluate",
                str(world / "map"),
                "-f",
                "tum",
                "--map-every",
                "2",
                "--map",
                str(db),
                "--structure",
                "tracks",
                "--seed",
                "3",
                "--json",
                str(summary),
                "--ray",
            ]
        )
        == 0
    )
    per_query = json.loads(summary.read_text())["per_query"]
    assert [q["name"] for q in per_query] == [r.name for r in local]
    for q, r in zip(per_query, local):  # same poses as the local run, query by query
        assert (q["status"], q["num_inliers"]) == (r.status, r.num_inliers)
        # Equal up to the last bits: Ray workers may sum in another order (alignment, threads).
        assert (q["center"] is None) == (r.estimate_center is None)
        if r.estimate_center is not None:
            np.testing.assert_allclose(q["center"], r.estimate_center, rtol=1e-9, atol=1e-12)


def check_ray_serve_deployment_serves_the_cli_pose(world: Path, tmp_path: Path) -> None:
    httpx = pytest.importorskip("httpx", reason="the serve extra is not installed")
    from ray import serve

    from planarloc.serve.ray_serve import deploy_fleet, session_shard

    db = build_map(read_dataset(world / "map", "tum"), tmp_path / "fleet.db")
    query = sorted((world / "query" / "rgb").glob("*.png"))[0]
    camera = (world / "query" / "camera.txt").read_text().splitlines()[-1]
    out = tmp_path / "poses.txt"
    assert main(["localize", "--map", str(db), str(query), "--camera", camera, "--out", str(out)]) == 0
    local = json.loads((tmp_path / "poses.txt.json.d" / f"{query.name}.json").read_text())
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    try:
        deploy_fleet({"office": db}, replicas=2, host="127.0.0.1", port=port, session_shards=2)
        url = f"http://127.0.0.1:{port}/v1/maps/office/localize"
        r = httpx.post(
            url, files={"image": (query.name, query.read_bytes())}, data={"camera": camera}, timeout=120
        )
        assert r.status_code == 200, r.text
        served = r.json()
        np.testing.assert_allclose(served["quat_wxyz"], local["quat_wxyz"], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(served["t"], local["t"], rtol=1e-9, atol=1e-12)
        bad = httpx.post(url, files={"image": ("x.png", b"nope")}, data={"camera": camera}, timeout=60)
        assert bad.status_code == 415 and "JPEG or PNG" in bad.json()["error"]
        # Sessions: each robot's frames are answered by one stream (frame numbers 1, 2, 3 of one
        # state), whichever shard its id hashes to; the shards of 4 robots are not all the same.
        frames = sorted((world / "query" / "rgb").glob("*.png"))[:3]
        robots = ["robot-1", "robot-2", "robot-3", "robot-4"]
        assert len({session_shard(r, 2) for r in robots}) == 2
        for robot in robots:
            numbers = []
            for k, image in enumerate(frames):
                r = httpx.post(
                    url,
                    files={"image": (image.name, image.read_bytes())},
                    data={"camera": camera, "session": robot, "stamp": str(0.1 * k)},
                    timeout=120,
                )
                assert r.status_code == 200, r.text
                assert r.json()["status"] in ("localized", "predicted", "lost")
                numbers.append(r.json()["session"]["frame"])
            assert numbers == [1, 2, 3], (robot, numbers)
        r = httpx.post(
            url,
            files={"image": (frames[0].name, frames[0].read_bytes())},
            data={"camera": camera, "session": "robot-1", "stamp": "0"},
            timeout=120,
        )
        assert r.status_code == 409
        status = serve.status().applications["planarloc-office"]
        assert status.status == "RUNNING"
        replicas = status.deployments["localizer-office"].replica_states
        assert replicas.get("RUNNING", 0) == 2
        assert all(
            status.deployments[f"sessions-office-{k}"].replica_states.get("RUNNING", 0) == 1 for k in (0, 1)
        )
    finally:
        serve.shutdown()


def test_ray_on_one_local_instance(world: Path, tmp_path: Path) -> None:
    """One test, so that pytest-xdist never starts two Ray instances (each takes ~20 s to start).
    4 logical CPUs (on any machine): the Serve check deploys 2 pool replicas and 2 session shards."""
    with RayBackend(num_cpus=4) as backend:
        check_map_build_on_ray_equals_local_build(world, tmp_path, backend)
        check_evaluate_on_ray_equals_local(world, tmp_path)
        check_ray_serve_deployment_serves_the_cli_pose(world, tmp_path)
    assert not ray.is_initialized()
