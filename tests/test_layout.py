"""The package's layout holds (README, "Layout"): imports flow downward through the layers, no
import cycle (a package ``__init__`` counts), front doors never import each other, no private name
crosses a package, and the base install imports none of the optional extras."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest
from fresh_python import python_stdout

ROOT = Path(__file__).resolve().parents[1] / "planarloc"
#: Layer of each top-level package: a module may import its own package and lower layers only.
LAYERS = {
    "extras": 0,
    "geometry": 0,
    "numerics": 0,
    "version": 0,
    "solvers": 1,
    "robust": 2,
    "features": 3,
    "gravity": 3,
    "map": 4,
    "localize": 5,
    "evaluation": 6,
    "io": 7,
    "synthetic": 7,
    "distributed": 8,
    "viz": 8,
    "client": 8,  # libraries of the front doors
    "compile": 8,  # compiling the kernels ahead (warmup, first use)
    "serve": 9,  # the service (FastAPI app, Ray Serve deployment)
    "ros2": 9,  # the ROS 2 node
    "cli": 10,  # the command line, which also launches the service
}
EXTRAS = (
    "fastapi",
    "uvicorn",
    "starlette",
    "multipart",
    "prometheus_client",
    "httpx",
    "ray",
    "rosbags",
    "evo",
    "rerun",
    "rclpy",
)


def _modules() -> dict[str, Path]:
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = path.relative_to(ROOT.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


MODULES = _modules()


def _imports(module: str) -> list[tuple[str, list[str], int]]:
    """``(imported module, names, line)`` of every import of ``module`` (also inside functions)."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno) for a in node.names if a.name.startswith("planarloc")]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(
                    package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else [])
                )
            if base.startswith("planarloc"):
                out.append((base, [a.name for a in node.names], node.lineno))
    return out


def _edges() -> dict[str, set[str]]:
    """Module -> the planarloc modules it imports (a name that is a submodule is that module)."""
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for module in MODULES:
        for target, names, _ in _imports(module):
            subs = [f"{target}.{n}" for n in names if f"{target}.{n}" in MODULES]
            graph[module] |= set(subs) if subs and len(subs) == len(names) else {target}
    return graph


def _layer(module: str) -> tuple[str, int] | None:
    parts = module.split(".")
    if len(parts) < 2:
        return None  # planarloc/__init__: the public facade
    return parts[1], LAYERS[parts[1]]


def test_every_package_has_a_layer() -> None:
    assert {m.split(".")[1] for m in MODULES if "." in m} == set(LAYERS)


def test_imports_flow_downward_and_front_doors_never_import_each_other() -> None:
    wrong = []
    for module, targets in _edges().items():
        here = _layer(module)
        for target in targets:
            there = _layer(target)
            if here is None or there is None or here[0] == there[0]:
                continue
            if there[1] >= here[1]:
                wrong.append(f"{module} (layer {here[1]}) imports {target} (layer {there[1]})")
    assert not wrong, "\n".join(wrong)


def test_the_service_never_imports_the_command_line() -> None:
    offenders = [
        f"{m} imports {t}"
        for m, ts in _edges().items()
        if m.startswith("planarloc.serve")
        for t in ts
        if t.startswith("planarloc.cli")
    ]
    assert not offenders


def test_no_import_cycles_package_inits_included() -> None:
    graph = _edges()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1 or v in graph[v]:
                cycles.append(sorted(component))

    sys.setrecursionlimit(10_000)
    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, cycles


def test_no_private_name_crosses_a_package() -> None:
    wrong = []
    for module in MODULES:
        package = module.rpartition(".")[0] if MODULES[module].name != "__init__.py" else module
        for target, names, line in _imports(module):
            private = [n for n in names if n.startswith("_") and not n.endswith("__")]
            private += [p for p in target.split(".") if p.startswith("_")][:1]
            owner = (
                target.rpartition(".")[0]
                if target in MODULES and not MODULES[target].name == "__init__.py"
                else target
            )
            if private and owner != package:
                wrong.append(f"{MODULES[module].relative_to(ROOT.parent)}:{line}: {target} {private}")
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize(
    "entry",
    [
        "planarloc",
        "planarloc.cli.main",
        "planarloc.localize.sequence",
        "planarloc.evaluation.queries",
        "planarloc.io.datasets",
        "planarloc.io.results",
        "planarloc.map.builder",
        "planarloc.serve.settings",
        "planarloc.ros2.node",
    ],
)
def test_the_base_install_imports_no_extra(entry: str) -> None:
    code = (
        f"import sys, {entry}; "
        f"print(' '.join(m for m in {EXTRAS!r} if m in sys.modules or any(k.startswith(m + '.') for k in "
        "sys.modules)))"
    )
    assert python_stdout(code, timeout=300).strip() == ""
