"""The ROS 2 node's fixtures: a map of the tiny world, a loopback-only ROS domain per test, and
`planarloc ros2` as a real subprocess."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from planarloc.io.datasets import read_dataset
from planarloc.map.builder import build_map
from planarloc.ros2.replay import NodeProcess, exclusive_domain, loopback_env


@pytest.fixture
def ros_domain(monkeypatch: pytest.MonkeyPatch) -> Iterator[int]:
    """A ROS domain held by this test alone, set in this process's environment for rclpy."""
    with exclusive_domain() as domain:
        for key, value in loopback_env(domain).items():
            monkeypatch.setenv(key, value)
        yield domain


@pytest.fixture(scope="session")
def world_map(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("ros2map") / "map.db"
    build_map(read_dataset(tiny_world / "map", "tum"), path)
    return path


@pytest.fixture
def start_node(ros_domain: int) -> Iterator:
    started: list[NodeProcess] = []

    def start(*args: object) -> NodeProcess:
        node = NodeProcess([str(a) for a in args], loopback_env(ros_domain))
        started.append(node)
        node.wait_ready()
        return node

    yield start
    for node in started:
        node.kill()
