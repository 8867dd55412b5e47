"""The node's parameters and the files generated from them, without ROS: ``planarloc ros2 --help``,
``share/params.yaml``, the launch file (run against stand-ins of ROS' ``launch`` package) and the
rviz configuration all agree with :class:`NodeSettings`."""

from __future__ import annotations

import ast
import runpy
import sys
import types
from dataclasses import fields
from pathlib import Path

import pytest

from planarloc.cli.main import build_parser
from planarloc.geometry.validation import InputError
from planarloc.ros2.settings import (
    NODE_NAME,
    PARAMETERS,
    SHARE_DIR,
    NodeSettings,
    check_parameter_names,
    parameter_help,
    params_file_names,
    params_yaml,
    yaml_value,
)

yaml = pytest.importorskip("yaml", reason="PyYAML comes with the ros2 extra (rclpy)")
DEFAULTS = {f.name: f.default for f in fields(NodeSettings)}


def test_params_yaml_lists_exactly_the_parameters_with_their_defaults() -> None:
    text = (SHARE_DIR / "params.yaml").read_text()
    assert text == params_yaml(), (
        "share/params.yaml is stale: regenerate it (planarloc.ros2.settings.params_yaml)"
    )
    loaded = yaml.safe_load(text)
    assert list(loaded) == [NODE_NAME] and list(loaded[NODE_NAME]) == ["ros__parameters"]
    params = loaded[NODE_NAME]["ros__parameters"]
    assert list(params) == list(PARAMETERS)
    for name, default in DEFAULTS.items():
        assert params[name] == default and type(params[name]) is type(default), name
    assert params["transform_tolerance_s"] == 1.0 and params["tf_broadcast"] is True
    assert params["map_frame_convention"] == "z_up"


def test_every_parameter_has_its_own_meaning() -> None:
    meaning = parameter_help()
    assert list(meaning) == list(PARAMETERS)
    assert all(len(text) > 15 for text in meaning.values())
    assert len(set(meaning.values())) == len(meaning)  # no shared, vague group text


def test_help_lists_every_parameter_with_its_default_and_an_example(capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as stop:
        build_parser().parse_args(["ros2", "--help"])
    assert stop.value.code == 0
    out = " ".join(capsys.readouterr().out.split())  # unwrapped
    for name, text in parameter_help().items():
        assert f" {name} = {yaml_value(DEFAULTS[name])}: {' '.join(text.split())}" in out, name
    assert "examples: planarloc ros2 --map" in out and "--params-file" in out and "planarloc.launch.py" in out


def test_share_dir_prints_the_folder_of_the_packaged_files(capsys: pytest.CaptureFixture) -> None:
    args = build_parser().parse_args(["ros2", "--share-dir"])
    assert args.func(args) == 0
    folder = Path(capsys.readouterr().out.strip())
    assert folder == SHARE_DIR
    assert {p.name for p in folder.iterdir()} >= {"planarloc.launch.py", "params.yaml", "planarloc.rviz"}


def test_running_without_a_map_is_an_error_naming_the_option() -> None:
    args = build_parser().parse_args(["ros2"])
    with pytest.raises(InputError, match="--map: give the map file"):
        args.func(args)


def test_settings_name_the_parameter_of_a_bad_value() -> None:
    with pytest.raises(InputError, match="parameter map_frame_convention: expected one of z_up, world"):
        NodeSettings(map="m.db", map_frame_convention="y_down")
    with pytest.raises(InputError, match="parameter transform_tolerance_s"):
        NodeSettings(map="m.db", transform_tolerance_s=-0.5)


def test_parameter_files_are_checked_for_unknown_names(tmp_path: Path) -> None:
    check_parameter_names(["--params-file", str(SHARE_DIR / "params.yaml"), "-p", "tf_broadcast:=false"])
    assert params_file_names(SHARE_DIR / "params.yaml") == list(PARAMETERS)
    typo = tmp_path / "typo.yaml"
    typo.write_text(
        "other_node:\n  ros__parameters:\n    anything: 1\n"
        "/**:\n  ros__parameters:\n    use_sim_time: true\n"
        "planarloc:\n  ros__parameters:\n    transform_tolerance: 0.5\n"
    )
    assert params_file_names(typo) == ["use_sim_time", "transform_tolerance"]  # other nodes' are theirs
    with pytest.raises(
        InputError, match=r"--params-file .*typo.yaml: unknown parameter 'transform_tolerance'"
    ):
        check_parameter_names(["--params-file", str(typo)])
    with pytest.raises(InputError, match="--params-file .*none.yaml"):
        check_parameter_names(["--params-file", str(tmp_path / "none.yaml")])
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(InputError, match="expected a mapping"):
        check_parameter_names(["--params-file", str(tmp_path / "list.yaml")])


class _Recorded:
    """A stand-in of a ROS launch class: records its arguments."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        self.args, self.kwargs = args, kwargs


def _fake_launch(monkeypatch: pytest.MonkeyPatch) -> None:
    names = {
        "launch": ["LaunchDescription"],
        "launch.actions": ["DeclareLaunchArgument", "ExecuteProcess"],
        "launch.conditions": ["IfCondition"],
        "launch.substitutions": ["LaunchConfiguration"],
    }
    for module, classes in names.items():
        fake = types.ModuleType(module)
        for cls in classes:
            setattr(fake, cls, type(cls, (_Recorded,), {}))
        monkeypatch.setitem(sys.modules, module, fake)


def test_the_launch_file_starts_planarloc_ros2_with_the_params_file(monkeypatch: pytest.MonkeyPatch) -> None:
    path = SHARE_DIR / "planarloc.launch.py"
    ast.parse(path.read_text())  # valid Python
    _fake_launch(monkeypatch)
    description = runpy.run_path(str(path))["generate_launch_description"]()
    entities = description.args[0]
    declared = {
        e.args[0]: e.kwargs.get("default_value")
        for e in entities
        if type(e).__name__ == "DeclareLaunchArgument"
    }
    assert declared == {
        "map": None,
        "params_file": str(SHARE_DIR / "params.yaml"),
        "planarloc": "planarloc",
        "rviz": "false",
    }
    node, rviz = [e for e in entities if type(e).__name__ == "ExecuteProcess"]
    # the command with the launch arguments substituted is one `planarloc ros2` accepts
    values = {"map": "office.db", "params_file": declared["params_file"], "planarloc": "planarloc"}
    cmd = [values[c.args[0]] if type(c).__name__ == "LaunchConfiguration" else c for c in node.kwargs["cmd"]]
    assert cmd[0] == "planarloc"
    args = build_parser().parse_args(cmd[1:])
    assert args.command == "ros2" and args.map == "office.db"
    assert args.ros_args == ["--params-file", str(SHARE_DIR / "params.yaml")]
    check_parameter_names(args.ros_args)
    assert rviz.kwargs["cmd"] == ["rviz2", "-d", str(SHARE_DIR / "planarloc.rviz")]
    assert rviz.kwargs["condition"].args[0].args == ("rviz",)


def test_the_rviz_config_shows_the_pose_with_covariance_tf_and_the_map_frame() -> None:
    config = yaml.safe_load((SHARE_DIR / "planarloc.rviz").read_text())["Visualization Manager"]
    assert config["Global Options"]["Fixed Frame"] == DEFAULTS["map_frame"]
    displays = {d["Class"]: d for d in config["Displays"]}
    pose = displays["rviz_default_plugins/PoseWithCovariance"]
    assert pose["Topic"]["Value"] == DEFAULTS["pose_topic"] and pose["Covariance"]["Value"] is True
    assert pose["Topic"]["Reliability Policy"] == "Reliable"  # the node publishes reliably
    assert displays["rviz_default_plugins/TF"]["Enabled"] is True
    assert displays["rviz_default_plugins/Image"]["Topic"]["Value"] == DEFAULTS["image_topic"]
    tools = {t["Class"]: t for t in config["Tools"]}
    assert tools["rviz_default_plugins/SetInitialPose"]["Topic"]["Value"] == DEFAULTS["initialpose_topic"]
