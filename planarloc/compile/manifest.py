"""The kernel list ``kernels.json`` (shipped next to this module): the kernels, their numba
signatures and compile seconds, and which kernels each warm-up step uses.

Its shape: ``{"kernels": {key: {"signatures": [str, ...], "compile_s": number}}, "steps": {step:
[key, ...]}}``, ``key`` being ``module:qualname``. After changing kernels, write it again with
``python -m planarloc.compile --write-manifest``.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from planarloc.compile.dispatchers import kernel_dependencies

MANIFEST = Path(__file__).with_name("kernels.json")
#: How to write the list again (said by :class:`ManifestError`).
WRITE_COMMAND = "python -m planarloc.compile --write-manifest"


@dataclass(frozen=True)
class Kernel:
    """A compiled kernel of the list: ``module:qualname``, its signatures (numba type reprs) and
    the CPU seconds its first compilation took where the list was written."""

    key: str
    signatures: tuple[str, ...]
    compile_s: float


@dataclass
class Manifest:
    """``kernels.json``: the kernels, and which of them each warm-up step uses."""

    kernels: dict[str, Kernel] = field(default_factory=dict)
    steps: dict[str, list[str]] = field(default_factory=dict)

    def for_steps(self, names: Iterable[str]) -> list[str]:
        """The kernels the given steps use: the ones they call from Python and every kernel those
        call (every kernel for an unknown step name)."""
        names = list(names)
        if any(n not in self.steps for n in names):
            return sorted(self.kernels)
        deps = kernel_dependencies(sorted(self.kernels))
        todo = [k for n in names for k in self.steps[n] if k in self.kernels]
        seen: set[str] = set()
        while todo:
            k = todo.pop()
            if k not in seen:
                seen.add(k)
                todo += deps.get(k, ())
        return sorted(seen)


class ManifestError(ValueError):
    """``kernels.json`` cannot be read, or is not the kernel list (names the file, one line)."""


def _shape_problem(raw: object) -> str | None:
    """What is wrong with the parsed ``kernels.json`` (module docstring: its shape), or None."""
    if not isinstance(raw, dict):
        return f"expected a JSON object, got {type(raw).__name__}"
    kernels, steps = raw.get("kernels"), raw.get("steps")
    if not isinstance(kernels, dict):
        return f"'kernels' must be an object of kernel entries, got {type(kernels).__name__}"
    if not isinstance(steps, dict):
        return f"'steps' must be an object of kernel lists, got {type(steps).__name__}"
    for key, entry in kernels.items():
        if not isinstance(entry, dict):
            return f"kernels[{key!r}] must be an object, got {type(entry).__name__}"
        sigs, seconds = entry.get("signatures"), entry.get("compile_s")
        if not isinstance(sigs, list) or not all(isinstance(x, str) for x in sigs):
            return f"kernels[{key!r}].signatures must be a list of strings"
        if isinstance(seconds, bool) or not isinstance(seconds, (int, float)):
            return f"kernels[{key!r}].compile_s must be a number, got {seconds!r}"
    for name, keys in steps.items():
        if not isinstance(keys, list) or not all(isinstance(k, str) for k in keys):
            return f"steps[{name!r}] must be a list of kernel names"
    return None


def load_manifest(path: Path | None = None) -> Manifest:
    """Read the kernel list (default: :data:`MANIFEST`, next to this module).

    Raises:
        ManifestError: the file cannot be read, is not JSON, or is not of the kernel list's shape
            (one line naming the file and how to write it again).
    """
    path = MANIFEST if path is None else Path(path)
    try:
        raw = json.loads(path.read_text())
    except OSError as exc:
        raise ManifestError(
            f"{path}: cannot read planarloc's kernel list ({exc.strerror or exc}); reinstall planarloc"
        ) from None
    except ValueError as exc:
        raise ManifestError(
            f"{path}: planarloc's kernel list is not JSON ({exc}); reinstall planarloc, or "
            f"write it again with `{WRITE_COMMAND}`"
        ) from None
    problem = _shape_problem(raw)
    if problem is not None:
        raise ManifestError(
            f"{path}: not planarloc's kernel list ({problem}); reinstall planarloc, or write it "
            f"again with `{WRITE_COMMAND}`"
        )
    kernels = {k: Kernel(k, tuple(v["signatures"]), float(v["compile_s"])) for k, v in raw["kernels"].items()}
    return Manifest(kernels, {s: list(ks) for s, ks in raw["steps"].items()})
