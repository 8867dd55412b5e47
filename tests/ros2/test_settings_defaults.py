"""The node's parameters that the library also has take the library's defaults
(:class:`LocalizerConfig`, :class:`RansacOptions`, :class:`SequenceConfig`): a changed library
default cannot silently diverge from the node's, its ``--help`` or its ``share/params.yaml``."""

from __future__ import annotations

from dataclasses import fields
from typing import Any

import pytest

from planarloc.geometry.validation import InputError
from planarloc.localize.localizer import LocalizerConfig
from planarloc.localize.stream_config import SequenceConfig
from planarloc.robust.options import Method, Structure
from planarloc.ros2.settings import MAX_PUBLISHED_STD_M, NodeSettings

LOC, SEQ = LocalizerConfig(), SequenceConfig()
#: node parameter -> the library's default it must equal
LIBRARY = {
    "method": LOC.method.value,
    "structure": LOC.ransac.structure.value,
    "seed": LOC.ransac.seed,
    "top_n": LOC.top_n,
    "max_position_std_m": LOC.ransac.max_position_std_m,
    "window": SEQ.window,
    "local_top_n": SEQ.local_top_n,
    "vo_model": SEQ.vo_model,
    "kidnap_confirmations": SEQ.kidnap_confirmations,
    "fixes": SEQ.fixes,
}


class _Declared:
    def __init__(self, value: object) -> None:
        self.value = value


class _FakeNode:
    """What :func:`declare_settings` calls on an rclpy node; records the declared defaults."""

    def __init__(self) -> None:
        self.declared: dict[str, object] = {}

    def declare_parameter(self, name: str, value: object, descriptor: Any) -> _Declared:
        self.declared[name] = value
        return _Declared(value)

    def set_parameters(self, params: list) -> None:
        pass


def test_the_node_field_defaults_are_the_librarys() -> None:
    defaults = {f.name: f.default for f in fields(NodeSettings)}
    for name, value in LIBRARY.items():
        assert defaults[name] == value and type(defaults[name]) is type(value), name
    assert isinstance(defaults["method"], str) and isinstance(
        defaults["structure"], str
    )  # ROS parameters: text
    assert LOC.method is Method.AUTO and LOC.ransac.structure is Structure.TRACKS


def test_the_declared_ros_parameters_default_to_the_library() -> None:
    pytest.importorskip("rcl_interfaces.msg", reason="the ros2 extra")
    from planarloc.ros2.node import declare_settings

    node = _FakeNode()
    settings = declare_settings(node, overrides={"map": "m.db"})
    for name, value in LIBRARY.items():
        assert node.declared[name] == value, name
    # the node's configurations are then the library's defaults, enums included
    assert settings.localizer_config() == LOC
    assert settings.localizer_config().method is Method.AUTO
    assert settings.sequence_config() == SEQ


def test_the_publishing_limit_is_a_named_node_setting() -> None:
    # Deliberately looser than the stream's own limit (BENCHMARKS.md, "The node's publishing limit").
    assert NodeSettings(map="m.db").max_published_std_m == MAX_PUBLISHED_STD_M >= SEQ.max_pose_std_m


def test_parameters_are_parsed_into_the_enums_at_the_edge() -> None:
    config = NodeSettings(map="m.db", method="2p1p", structure="none", seed=3).localizer_config()
    assert (
        config.method is Method.P2P1 and config.ransac.structure is Structure.NONE and config.ransac.seed == 3
    )
    for name in ("method", "structure"):
        with pytest.raises(InputError, match=f"parameter {name}: expected one of"):
            NodeSettings(map="m.db", **{name: "bogus"})


def test_the_coarse_pass_parameter_keeps_the_feature_types_default_unless_set() -> None:
    assert NodeSettings(map="m.db").localizer_config().coarse_keypoints is None  # -1: the type's
    assert NodeSettings(map="m.db", coarse_keypoints=0).localizer_config().coarse_keypoints == 0
    assert NodeSettings(map="m.db", coarse_keypoints=1500).localizer_config().coarse_keypoints == 1500
    with pytest.raises(InputError, match="parameter coarse_keypoints: expected -1"):
        NodeSettings(map="m.db", coarse_keypoints=-2)
