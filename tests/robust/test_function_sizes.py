"""Sizes in ``planarloc.robust``: at most 12 parameters and 80 lines (docstring excluded) per
function, nested ones included, and at most 600 lines per module.

A numba kernel that grew too large once waited in ``KERNELS_TO_SPLIT`` at its size until it was
split into named stages or took the problem's named record
(:class:`planarloc.robust.problem.ProblemArrays`, which the shipped kernel list
``planarloc/compile/kernels.json`` names); every one has been, and the list may only shrink.
"""

from __future__ import annotations

import ast
from pathlib import Path

import planarloc.robust

MAX_PARAMETERS = 12
MAX_LINES = 80
MAX_MODULE_LINES = 600

# (module, function): (parameters, lines) of numba kernels still too large; see the module docstring.
KERNELS_TO_SPLIT: dict[tuple[str, str], tuple[int, int]] = {}


def function_sizes(path: Path) -> dict[str, tuple[int, int, bool]]:
    """``name: (parameters, lines without the docstring, is a numba kernel)`` of every function
    (methods and nested functions too, by qualified name)."""
    out = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = child.args
                params = (
                    len(a.posonlyargs)
                    + len(a.args)
                    + len(a.kwonlyargs)
                    + (a.vararg is not None)
                    + (a.kwarg is not None)
                )
                lines = child.end_lineno - child.lineno + 1
                if ast.get_docstring(child, clean=False) is not None:
                    lines -= child.body[0].end_lineno - child.body[0].lineno + 1
                kernel = any("njit" in ast.unparse(d) for d in child.decorator_list)
                out[prefix + child.name] = (params, lines, kernel)
                visit(child, prefix + child.name + ".")
            elif isinstance(child, ast.ClassDef):
                visit(child, prefix + child.name + ".")

    visit(ast.parse(path.read_text(encoding="utf-8")), "")
    return out


def _all_sizes() -> dict[tuple[str, str], tuple[int, int, bool]]:
    root = Path(planarloc.robust.__file__).parent
    return {
        (p.stem, name): size for p in sorted(root.glob("*.py")) for name, size in function_sizes(p).items()
    }


def test_every_function_is_within_the_limits() -> None:
    sizes = _all_sizes()
    assert len(sizes) > 150  # the walk sees the package
    over = {
        k: v[:2]
        for k, v in sizes.items()
        if (v[0] > MAX_PARAMETERS or v[1] > MAX_LINES) and k not in KERNELS_TO_SPLIT
    }
    assert over == {}


def test_the_kernels_left_to_split_do_not_grow_and_the_list_only_shrinks() -> None:
    sizes = _all_sizes()
    for key, (params, lines) in KERNELS_TO_SPLIT.items():
        assert key in sizes, f"{key} is gone: remove it from KERNELS_TO_SPLIT"
        p, n, kernel = sizes[key]
        assert kernel, f"{key} is plain Python: split it"
        assert p <= params and n <= lines, (key, (p, n))
        assert p > MAX_PARAMETERS or n > MAX_LINES, f"{key} is within the limits now: remove it from the list"


def test_every_module_is_within_the_limit() -> None:
    root = Path(planarloc.robust.__file__).parent
    lines = {p.stem: len(p.read_text(encoding="utf-8").splitlines()) for p in sorted(root.glob("*.py"))}
    assert len(lines) > 20  # the walk sees the package
    assert {m: n for m, n in lines.items() if n > MAX_MODULE_LINES} == {}


def test_the_counter_counts_parameters_and_lines(tmp_path: Path) -> None:
    f = tmp_path / "m.py"
    f.write_text(
        'def f(a, b=1, *c, d, **e):\n    """Doc\n    string."""\n    x = 1\n    return x\n\n\n'
        "class K:\n    def g(self):\n        def h():\n            pass\n        return h\n"
    )
    assert function_sizes(f) == {"f": (5, 3, False), "K.g": (1, 4, False), "K.g.h": (0, 2, False)}
