"""``tf2_msgs/msg/TFMessage`` for a ROS 2 installed from PyPI.

PyPI has wheels of rclpy and of the common message packages (``ros-geometry-msgs``,
``ros-sensor-msgs``, ``ros-nav-msgs``, ``ros-diagnostic-msgs``), but none of ``tf2_msgs``, the
type of ``/tf`` and ``/tf_static``. The rosidl code generators come with those wheels, so
:func:`tf_message_type` builds the one message the node needs, ``tf2_msgs/msg/TFMessage``
(``geometry_msgs/TransformStamped[] transforms``, as in ROS' ``geometry2``), the way
``rosidl_generate_interfaces`` does: generated C and Python code for the C, Fast DDS and
introspection type supports, compiled with the system C/C++ compiler (``CC`` / ``CXX``, default
``gcc`` / ``g++``) into a cache folder (``$PLANARLOC_CACHE`` or ``$XDG_CACHE_HOME/planarloc``,
default ``~/.cache/planarloc``), once per ROS and Python version (about 5 s). The type's name and
its type hash are those of ROS' own ``tf2_msgs``, so it talks to any ROS 2 node (nav2, rviz,
tf2_ros). A ROS installation's ``tf2_msgs`` (a sourced ``/opt/ros/...``) is used when importable.
"""

from __future__ import annotations

import ctypes
import hashlib
import importlib
import importlib.metadata
import logging
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path
from typing import Any

from planarloc.extras import MissingExtraError

logger = logging.getLogger(__name__)

PACKAGE = "tf2_msgs"
#: the IDL that rosidl_adapter makes of geometry2's tf2_msgs/msg/TFMessage.msg
TF_MESSAGE_IDL = """\
// generated from rosidl_adapter/resource/msg.idl.em
// with input from tf2_msgs/msg/TFMessage.msg
// generated code does not contain a copyright notice

#include "geometry_msgs/msg/TransformStamped.idl"

module tf2_msgs {
  module msg {
    struct TFMessage {
      sequence<geometry_msgs::msg::TransformStamped> transforms;
    };
  };
};
"""
#: the generators run by rosidl_generate_interfaces for Python and Fast DDS (module, class)
GENERATORS = {
    "c": ("rosidl_generator_c.cli", "GenerateC"),
    "typesupport_c": ("rosidl_typesupport_c.cli", "GenerateCTypesupport"),
    "typesupport_fastrtps_c": ("rosidl_typesupport_fastrtps_c.cli", "GenerateFastRTPSCTypesupport"),
    "typesupport_introspection_c": (
        "rosidl_typesupport_introspection_c.cli",
        "GenerateIntrospectionCTypesupport",
    ),
    "py": ("rosidl_generator_py.cli", "GeneratePython"),
}
_GENERATE = """
import importlib, pathlib, sys
out, idl, include, specs = pathlib.Path(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4:]
for spec in specs:
    name, module, cls = spec.split(":")
    ext = getattr(importlib.import_module(module), cls)(name)
    ext.generate("tf2_msgs", [idl], [include], out / name)
"""


class InterfaceBuildError(MissingExtraError):
    """``tf2_msgs`` is neither installed nor buildable here; the message says what is missing."""


def cache_root() -> Path:
    """The folder of planarloc's built ROS interfaces."""
    base = os.environ.get("PLANARLOC_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "planarloc"
    )
    return Path(base) / "ros2-interfaces"


def _ros_prefix() -> Path:
    """The prefix (``include/``, ``lib/``, ``share/``) of the installed geometry_msgs."""
    try:
        from ament_index_python.packages import get_package_prefix

        return Path(get_package_prefix("geometry_msgs"))
    except Exception:  # pip-installed ROS: the prefix is the environment's, without AMENT_PREFIX_PATH
        prefix = Path(sys.prefix)
        if (prefix / "share" / "geometry_msgs" / "msg" / "TransformStamped.idl").is_file():
            return prefix
    raise InterfaceBuildError(
        "cannot build tf2_msgs: geometry_msgs' interface files are not installed; "
        "install the extra: pip install 'planarloc[ros2]'"
    )


def _build_key(prefix: Path) -> str:
    versions = []
    for dist in (
        "ros-geometry-msgs",
        "ros-rosidl-generator-py",
        "ros-rosidl-typesupport-fastrtps-c",
        "ros-rclpy",
    ):
        try:
            versions.append(f"{dist}={importlib.metadata.version(dist)}")
        except importlib.metadata.PackageNotFoundError:
            versions.append(f"{dist}=?")
    text = "|".join(
        [str(prefix.resolve()), sysconfig.get_config_var("EXT_SUFFIX") or "", *versions, TF_MESSAGE_IDL]
    )
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def _compiler(var: str, default: str) -> str:
    exe = shutil.which(os.environ.get(var, default))
    if exe is None:
        raise InterfaceBuildError(
            f"tf2_msgs (the type of /tf) is not installed and cannot be built: no C/C++ compiler "
            f"({var}={os.environ.get(var, default)}); install gcc and g++ (apt-get install g++), or source a "
            "ROS 2 installation that has tf2_msgs"
        )
    return exe


def _run(cmd: list[str], cwd: Path, env: dict[str, str] | None = None) -> None:
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        tail = " ".join((proc.stderr or proc.stdout).strip().splitlines()[-3:])
        raise InterfaceBuildError(
            f"building tf2_msgs failed: {Path(cmd[0]).name} exited {proc.returncode}: {tail}"
        )


def build_tf2_msgs(out: Path, prefix: Path) -> None:
    """Generate and compile ``tf2_msgs`` (TFMessage only) into ``out`` (a new folder):
    ``out/tf2_msgs`` (the Python package) and ``out/lib`` (its shared libraries)."""
    cc, cxx = _compiler("CC", "gcc"), _compiler("CXX", "g++")
    import numpy

    work = out / "build"
    (work / "idl" / "msg").mkdir(parents=True)
    (work / "idl" / "msg" / "TFMessage.idl").write_text(TF_MESSAGE_IDL)
    env = dict(os.environ)
    env["AMENT_PREFIX_PATH"] = os.pathsep.join(filter(None, [str(prefix), env.get("AMENT_PREFIX_PATH")]))
    specs = [f"{name}:{module}:{cls}" for name, (module, cls) in GENERATORS.items()]
    gen = work / "gen"
    _run(
        [
            sys.executable,
            "-c",
            _GENERATE,
            str(gen),
            f"{work / 'idl'}:msg/TFMessage.idl",
            str(prefix / "share"),
            *specs,
        ],
        work,
        env,
    )
    include = work / "include" / PACKAGE
    for name in ("c", "typesupport_fastrtps_c", "typesupport_introspection_c"):
        for header in (gen / name).rglob("*.h"):
            target = include / header.relative_to(gen / name)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(header, target)
    inc = prefix / "include"
    flags = [
        "-shared",
        "-fPIC",
        "-O2",
        f"-I{work / 'include'}",
        f"-I{inc}",
        *[f"-I{d}" for d in sorted(inc.iterdir()) if d.is_dir()],
        f"-I{sysconfig.get_paths()['include']}",
        f"-I{numpy.get_include()}",
    ]
    lib = out / "lib"
    lib.mkdir()
    link = [f"-L{lib}", f"-L{prefix / 'lib'}", f"-Wl,-rpath,{prefix / 'lib'}"]
    libraries = _tf2_libraries(cc, cxx, gen)
    for compiler, sources, name, libs in libraries:
        extra = ["-std=c++17"] if compiler == cxx else []
        soname = f"lib{PACKAGE}__{name}.so"
        _run(
            [
                compiler,
                *flags,
                *extra,
                *map(str, sources),
                "-o",
                str(lib / soname),
                f"-Wl,-soname,{soname}",
                *link,
                "-Wl,-rpath,$ORIGIN",
                *[f"-l{x}" for x in libs],
            ],
            work,
        )
    _build_tf2_package(out, gen, cc, flags, link, work)
    shutil.rmtree(work)


def _tf2_libraries(cc: str, cxx: str, gen: Path) -> list[tuple[str, list[Path], str, list[str]]]:
    """The shared libraries of the tf2_msgs interface: (compiler, sources, library, libraries linked)."""
    detail = "msg/detail"
    return [  # (compiler, sources, library, libraries linked), in dependency order
        (
            cc,
            sorted((gen / "c" / detail).glob("*.c")),
            "rosidl_generator_c",
            ["rosidl_runtime_c", "rcutils", "geometry_msgs__rosidl_generator_c"],
        ),
        (
            cc,
            [gen / "typesupport_introspection_c" / detail / "tf_message__type_support.c"],
            "rosidl_typesupport_introspection_c",
            [
                "tf2_msgs__rosidl_generator_c",
                "rosidl_runtime_c",
                "geometry_msgs__rosidl_typesupport_introspection_c",
            ],
        ),
        (
            cxx,
            [gen / "typesupport_fastrtps_c" / detail / "tf_message__type_support_c.cpp"],
            "rosidl_typesupport_fastrtps_c",
            [
                "tf2_msgs__rosidl_generator_c",
                "rosidl_runtime_c",
                "rosidl_typesupport_fastrtps_c",
                "rosidl_typesupport_fastrtps_cpp",
                "fastcdr",
                "rmw",
                "geometry_msgs__rosidl_typesupport_fastrtps_c",
                "geometry_msgs__rosidl_generator_c",
            ],
        ),
        (
            cxx,
            [gen / "typesupport_c" / "msg" / "tf_message__type_support.cpp"],
            "rosidl_typesupport_c",
            [
                "tf2_msgs__rosidl_generator_c",
                "rosidl_runtime_c",
                "rosidl_typesupport_c",
                "rcpputils",
                "rcutils",
            ],
        ),
        (
            cc,
            [gen / "py" / "msg" / "_tf_message_s.c"],
            "rosidl_generator_py",
            [
                "tf2_msgs__rosidl_generator_c",
                "geometry_msgs__rosidl_generator_py",
                "geometry_msgs__rosidl_generator_c",
                "rosidl_runtime_c",
            ],
        ),
    ]


def _build_tf2_package(out: Path, gen: Path, cc: str, flags: list[str], link: list[str], work: Path) -> None:
    """The Python package: the generated message modules and their type-support extensions."""
    package = out / PACKAGE
    (package / "msg").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    for py in (gen / "py" / "msg").glob("*.py"):
        shutil.copy2(py, package / "msg" / py.name)
    suffix = sysconfig.get_config_var("EXT_SUFFIX")
    for ts in ("c", "fastrtps_c", "introspection_c"):
        _run(
            [
                cc,
                *flags,
                str(gen / "py" / f"_{PACKAGE}_s.ep.rosidl_typesupport_{ts}.c"),
                "-o",
                str(package / f"{PACKAGE}_s__rosidl_typesupport_{ts}{suffix}"),
                *link,
                "-Wl,-rpath,$ORIGIN/../lib",
                f"-l{PACKAGE}__rosidl_generator_py",
                f"-l{PACKAGE}__rosidl_typesupport_{ts}",
                f"-l{PACKAGE}__rosidl_generator_c",
            ],
            work,
        )


def tf_message_type() -> Any:
    """The ``tf2_msgs.msg.TFMessage`` class: the installed one, else planarloc's build of it
    (made on first use, see the module docstring).

    Raises:
        InterfaceBuildError: not installed and not buildable (no compiler, no geometry_msgs);
            the message says what to install.
    """
    try:
        return importlib.import_module(f"{PACKAGE}.msg").TFMessage
    except ImportError:
        pass
    prefix = _ros_prefix()
    root = cache_root() / f"{PACKAGE}-{_build_key(prefix)}"
    if not (root / PACKAGE / "msg" / "_tf_message.py").is_file():
        root.parent.mkdir(parents=True, exist_ok=True)
        logger.info("building %s (TFMessage) into %s", PACKAGE, root)
        tmp = Path(tempfile.mkdtemp(prefix=f".{PACKAGE}-", dir=root.parent))
        try:
            build_tf2_msgs(tmp / "out", prefix)
            try:
                os.replace(tmp / "out", root)
            except OSError:  # built concurrently by another process: keep that one
                if not (root / PACKAGE / "msg" / "_tf_message.py").is_file():
                    raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    # The C type support dlopen()s its Fast DDS and introspection libraries by name when the first
    # publisher or subscription is made; loaded here first, the loader finds them by their soname.
    for ts in ("introspection_c", "fastrtps_c"):
        ctypes.CDLL(str(root / "lib" / f"lib{PACKAGE}__rosidl_typesupport_{ts}.so"), mode=ctypes.RTLD_GLOBAL)
    sys.path.insert(0, str(root))
    importlib.invalidate_caches()
    return importlib.import_module(f"{PACKAGE}.msg").TFMessage
