"""`planarloc warmup`: compile every numba kernel a query uses into numba's on-disk cache, on all cores.

numba compiles a kernel on its first call and caches the machine code next to the module
(``__pycache__/*.nbi, *.nbc``). Compiling planarloc's kernels takes about 170 s of CPU (kernels.json), so a
fresh install or container would pay it on its first query; ``planarloc warmup`` at install or
image-build time (``RUN planarloc warmup`` after ``pip install``, as root, before ``USER``) writes
the cache once, and queries only load it, also as a user who cannot write the install
(:mod:`planarloc.numerics.kernel_cache`; the repository's ``Dockerfile`` does this).

How it compiles in parallel: ``kernels.json`` (next to this module) lists, for each warm-up step
(:func:`warmup_steps`: a method with a structure mode on a small generated scene, the degeneracy
analysis, the single-call solvers), the kernels it uses with their numba signatures and the CPU
seconds their compilation took. ``--jobs`` worker processes (default: one per core) each compile
one kernel at a time, handed out once every kernel it calls (read from its bytecode) is in the
cache, longest remaining chain first; a worker loads those callees from the cache instead of
compiling them again. Then the steps run once here: that loads every kernel and compiles
whatever the list missed (a kernel changed since the list was written is compiled there, only
without the parallelism). After changing kernels, regenerate the list with
``python -m planarloc.cli.warmup_command --write-manifest``.

The commands that estimate poses call :func:`compile_ahead`: when kernels of their method are
not in the cache, they say so in one line on stderr and compile them the same way first. A kernel
list that cannot be read, or is not of its shape, fails ``warmup`` with one line naming the file;
the other commands warn in one line and let the kernels compile on first use.
"""

from __future__ import annotations

import argparse
import ast
import dis
import importlib
import json
import logging
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from planarloc.cli.commands import add_command
from planarloc.cli.console import info, note, progress_bar
from planarloc.cli.exit_codes import WARMUP_RESUMES

logger = logging.getLogger(__name__)

MANIFEST = Path(__file__).with_name("kernels.json")
Update = Callable[[str, int, int], None]
COMPILE_STAGE = "compile kernels"


# ---- the warm-up steps -----------------------------------------------------------------------------
def step_name(method: str, structure: str) -> str:
    """The warm-up step of one estimator configuration, e.g. ``"auto tracks"``."""
    return f"{method} {structure}"


def warmup_steps() -> list[tuple[str, Callable[[], object]]]:
    """``(name, run)`` of every warm-up step: each method with ``structure="none"`` and
    ``"tracks"`` on a spread scene, 2p1p on a collinear scene (the degeneracy analysis: map
    covariance and cost profile), and the single-call solver APIs."""
    import planarloc.solvers as S
    from planarloc.geometry.pose import Pose
    from planarloc.robust.absolute_pose import estimate_absolute_pose
    from planarloc.robust.options import Method, RansacOptions
    from planarloc.synthetic.scenes import make_scene

    rng = np.random.default_rng(0)
    spread = make_scene(rng, num_refs=3, matches_per_pair=30, noise_px=1.0, outlier_ratio=0.3, track_pool=1.5)
    line = make_scene(rng, num_refs=3, matches_per_pair=30, noise_px=1.0, outlier_ratio=0.2, collinear=True)
    opts = RansacOptions(max_iterations=20, min_iterations=20)
    steps: list[tuple[str, Callable[[], object]]] = [
        (step_name(m.value, s), lambda m=m, s=s: estimate_absolute_pose(
            spread.query_camera, spread.pairs, m, RansacOptions(max_iterations=20, min_iterations=20, structure=s)))
        for m in Method for s in ("none", "tracks")]
    steps.append(("2p1p collinear", lambda: estimate_absolute_pose(line.query_camera, line.pairs, "2p1p", opts)))
    xq = np.array([[0.1, 0.2, 1.0], [-0.3, 0.1, 1.0], [0.2, -0.1, 1.0], [0.05, 0.3, 1.0], [-0.2, -0.2, 1.0],
                   [0.3, 0.25, 1.0], [-0.1, 0.05, 1.0], [0.15, -0.3, 1.0]])
    xr = xq + np.array([0.02, 0.0, 0.0])
    rel = Pose.from_center(np.eye(3), np.array([1.0, 0.0, 0.0]))  # unit baseline to a reference
    ref1, ref2 = Pose.identity(), Pose.from_center(np.eye(3), np.array([0.0, 0.0, 2.0]))
    steps.append(("solvers", lambda: (S.relpose_planar_2p(xq[:2], xr[:2]), S.relpose_5p_nister(xq[:5], xr[:5]),
                                      S.relpose_5p_stewenius(xq[:5], xr[:5]), S.relpose_8p(xq, xr),
                                      S.essentials_5p_nister(xq[:5], xr[:5]),
                                      S.essentials_5p_stewenius(xq[:5], xr[:5]), S.essential_8p(xq, xr),
                                      S.abspose_up2p(xq[:2], 5 * xq[:2]), S.abspose_2p2p(rel, rel, ref1, ref2),
                                      S.abspose_2p1p(rel, ref1, ref2, xq[0], xr[0]))))
    return steps


def run_steps(names: Iterable[str] | None = None, update: Update | None = None) -> dict[str, float]:
    """Run warm-up steps (all by default) in this process; returns seconds per step."""
    steps = warmup_steps()
    if names is not None:
        wanted = set(names)
        steps = [s for s in steps if s[0] in wanted]
    times = {}
    if update is not None:
        update("run steps", 0, len(steps))
    for i, (name, fn) in enumerate(steps):
        t0 = time.perf_counter()
        fn()
        times[name] = time.perf_counter() - t0
        if update is not None:
            update("run steps", i + 1, len(steps))
    return times


# ---- the kernel list -------------------------------------------------------------------------------
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


def _manifest_shape_problem(raw: object) -> str | None:
    """What is wrong with the parsed ``kernels.json`` (its documented shape: ``{"kernels": {key:
    {"signatures": [str, ...], "compile_s": number}}, "steps": {step: [key, ...]}}``), or None."""
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
            (one line naming the file; ``python -m planarloc.cli.warmup_command --write-manifest``
            writes it again).
    """
    path = MANIFEST if path is None else Path(path)
    try:
        raw = json.loads(path.read_text())
    except OSError as exc:
        raise ManifestError(f"{path}: cannot read planarloc's kernel list ({exc.strerror or exc}); reinstall "
                            "planarloc") from None
    except ValueError as exc:
        raise ManifestError(f"{path}: planarloc's kernel list is not JSON ({exc}); reinstall planarloc, or "
                            "write it again with `python -m planarloc.cli.warmup_command --write-manifest`") from None
    problem = _manifest_shape_problem(raw)
    if problem is not None:
        raise ManifestError(f"{path}: not planarloc's kernel list ({problem}); reinstall planarloc, or write it "
                            "again with `python -m planarloc.cli.warmup_command --write-manifest`")
    kernels = {k: Kernel(k, tuple(v["signatures"]), float(v["compile_s"])) for k, v in raw["kernels"].items()}
    return Manifest(kernels, {s: list(ks) for s, ks in raw["steps"].items()})


def _dispatcher(key: str):
    """The numba dispatcher ``module:qualname``, or None if there is none of that name."""
    from numba.core.dispatcher import Dispatcher

    module, _, qualname = key.partition(":")
    try:
        obj = importlib.import_module(module)
        for part in qualname.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError):
        return None
    return obj if isinstance(obj, Dispatcher) else None


def _numba_types() -> dict[str, object]:
    from numba.core import types

    names = {k: v for k, v in vars(types).items() if not k.startswith("_")}
    names["bool"] = types.boolean  # repr(types.boolean) is 'bool'
    names["omitted"] = lambda default: types.Omitted(default)  # repr: 'omitted(default=...)'
    return names


#: The expressions a signature in ``kernels.json`` may use: type names, calls and subscripts of them
#: (``array(float64, 1d, C)``, ``Literal[int](0)``), constants and tuples; no operators or attributes.
_SIGNATURE_NODES = (ast.Expression, ast.Tuple, ast.Name, ast.Call, ast.keyword, ast.Subscript, ast.Constant,
                    ast.Load, ast.UnaryOp, ast.USub)


def parse_signature(text: str, names: dict[str, object] | None = None) -> tuple | None:
    """The argument types of a signature written as ``repr(tuple_of_numba_types)``; None if it
    does not parse (e.g. a literal type) or is not made only of numba type names, calls, constants
    and tuples (the list is data: it is never evaluated as code beyond that)."""
    try:
        if not isinstance(text, str) or len(text) > 4000 or not all(
                isinstance(n, _SIGNATURE_NODES) for n in ast.walk(ast.parse(text, mode="eval"))):
            return None
        sig = eval(text, {"__builtins__": {}}, names or _numba_types())  # noqa: S307 - numba type names only
    except Exception:  # noqa: BLE001 - any failure: the kernel is compiled by the steps instead
        return None
    return sig if isinstance(sig, tuple) else None


def missing_kernels(keys: Iterable[str], manifest: Manifest) -> list[str]:
    """The kernels among ``keys`` with a signature that numba's cache does not hold for this
    machine (numba's cache index, read as ``Dispatcher.compile`` reads it). If the cache cannot
    be inspected (another numba version), none are reported missing: numba compiles lazily."""
    names = _numba_types()
    out = []
    try:
        for key in keys:
            d = _dispatcher(key)
            if d is None:
                continue
            cache = d._cache
            if not hasattr(cache, "_cache_file"):  # not a cache=True kernel
                continue
            index = cache._cache_file._load_index()
            codegen = d.targetctx.codegen()
            for text in manifest.kernels[key].signatures:
                sig = parse_signature(text, names)
                if sig is not None and cache._index_key(sig, codegen) not in index:
                    out.append(key)
                    break
    except Exception as exc:  # noqa: BLE001 - numba internals changed: behave as before (lazy)
        logger.info("cannot inspect numba's cache (%s); kernels compile on first use", exc)
        return []
    return out


def _kernels_persist(key: str) -> bool:
    """Whether kernels compiled in worker processes would reach this one (through numba's cache)."""
    from planarloc.numerics.kernel_cache import kernels_persist

    d = _dispatcher(key)
    return d is not None and kernels_persist(d._cache)


def _direct_callees(d) -> set:
    """Dispatchers a kernel names in its bytecode (``f(...)`` and ``module.f(...)``)."""
    from numba.core.dispatcher import Dispatcher

    out, prev = set(), None
    for ins in dis.get_instructions(d.py_func):
        value = None
        if ins.opname == "LOAD_GLOBAL":
            value = d.py_func.__globals__.get(ins.argval)
        elif ins.opname in ("LOAD_ATTR", "LOAD_METHOD") and type(prev).__name__ == "module":
            value = getattr(prev, ins.argval, None)
        if isinstance(value, Dispatcher):
            out.add(value)
        prev = value
    return out


def kernel_dependencies(keys: Sequence[str]) -> dict[str, set[str]]:
    """For each kernel, the kernels among ``keys`` it calls, directly or through kernels that are
    inlined into it (``inline="always"``: compiled as part of the caller)."""
    dispatchers = {k: _dispatcher(k) for k in keys}
    key_of = {d: k for k, d in dispatchers.items() if d is not None}
    memo: dict[object, set] = {}

    def calls(d, seen: frozenset) -> set:
        if d in memo:
            return memo[d]
        out = set()
        for c in _direct_callees(d):
            if c in seen:
                continue
            if c.targetoptions.get("inline") == "always":
                out |= calls(c, seen | {c})
            else:
                out.add(c)
        memo[d] = out
        return out

    return {k: ({key_of[c] for c in calls(d, frozenset({d})) if c in key_of} - {k}) if d is not None else set()
            for k, d in dispatchers.items()}


# ---- compiling on several cores --------------------------------------------------------------------
class _Schedule:
    """Hands out kernels whose callees are compiled, longest remaining chain of compile time first."""

    def __init__(self, deps: dict[str, set[str]], cost: dict[str, float]) -> None:
        self.deps, self.pending, self.running, self.done = deps, set(deps), set(), set()
        users: dict[str, set[str]] = {k: set() for k in deps}
        for k, ds in deps.items():
            for d in ds:
                users[d].add(k)
        self.chain: dict[str, float] = {}

        def chain(k: str, seen: frozenset) -> float:
            if k not in self.chain:
                self.chain[k] = cost.get(k, 1.0) + max((chain(u, seen | {k}) for u in users[k] if u not in seen),
                                                       default=0.0)
            return self.chain[k]

        for k in deps:
            chain(k, frozenset())
        self._cv = threading.Condition()

    def take(self) -> str | None:
        with self._cv:
            while self.pending:
                ready = [k for k in self.pending if self.deps[k] <= self.done]
                if not ready and not self.running:
                    ready = list(self.pending)  # a call cycle: compile one anyway
                if ready:
                    k = max(ready, key=lambda r: (self.chain[r], r))
                    self.pending.discard(k)
                    self.running.add(k)
                    return k
                self._cv.wait()
            return None

    def finish(self, key: str) -> None:
        with self._cv:
            self.running.discard(key)
            self.done.add(key)
            self._cv.notify_all()


@dataclass
class CompileReport:
    """What :func:`compile_kernels` did."""

    compiled: int = 0
    failed: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0


def compile_kernels(keys: Sequence[str], manifest: Manifest, jobs: int | None = None,
                    update: Update | None = None) -> CompileReport:
    """Compile kernels into numba's on-disk cache in ``jobs`` worker processes (see the module
    docstring). Returns what was compiled and what failed (those compile on first use)."""
    t0 = time.perf_counter()
    keys = sorted(set(keys) & set(manifest.kernels))
    report = CompileReport()
    if not keys:
        return report
    schedule = _Schedule(kernel_dependencies(keys), {k: manifest.kernels[k].compile_s for k in keys})
    jobs = max(1, min(int(jobs or os.cpu_count() or 1), len(keys)))
    lock = threading.Lock()
    if update is not None:
        update(COMPILE_STAGE, 0, len(keys))
    workers = [subprocess.Popen([sys.executable, "-m", "planarloc.cli.warmup_command", "--compile-worker"],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
               for _ in range(jobs)]

    def drive(proc: subprocess.Popen) -> None:
        while (key := schedule.take()) is not None:
            try:
                proc.stdin.write(json.dumps({"key": key, "signatures": manifest.kernels[key].signatures}) + "\n")
                proc.stdin.flush()
                reply = proc.stdout.readline()
            except (OSError, ValueError):
                reply = ""
            errors = json.loads(reply)["errors"] if reply else ["the worker process ended"]
            schedule.finish(key)
            with lock:
                if errors:
                    report.failed[key] = "; ".join(errors)
                else:
                    report.compiled += 1
                done = len(schedule.done)
            if update is not None:
                update(COMPILE_STAGE, done, len(keys))
            if not reply:
                return

    threads = [threading.Thread(target=drive, args=(p,), daemon=True) for p in workers]
    try:
        for t in threads:
            t.start()
        for t in threads:
            while t.is_alive():
                t.join(0.2)
    finally:
        for p in workers:
            if p.poll() is None:
                try:
                    p.stdin.close()
                except OSError:
                    pass
        for p in workers:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
    report.seconds = time.perf_counter() - t0
    return report


def _compile_worker() -> int:
    """A worker process: compile the kernels named on stdin, one JSON line each, and answer each
    with ``{"key", "seconds", "errors"}``."""
    names = _numba_types()
    for line in sys.stdin:
        task = json.loads(line)
        t0, errors = time.process_time(), []
        d = _dispatcher(task["key"])
        for text in task["signatures"]:
            sig = parse_signature(text, names)
            if d is None or sig is None:
                errors.append(f"{task['key']}{text}: no such kernel or signature")
                continue
            try:
                d.compile(sig)
            except Exception as exc:  # noqa: BLE001 - reported; the kernel compiles on first use
                errors.append(f"{task['key']}{text}: {type(exc).__name__}: {exc}".splitlines()[0])
        print(json.dumps({"key": task["key"], "seconds": time.process_time() - t0, "errors": errors}), flush=True)
    return 0


# ---- what the commands call --------------------------------------------------------------------------
def steps_for(configs: Iterable[object]) -> list[str]:
    """The warm-up steps that localizing with these :class:`~planarloc.localize.localizer.LocalizerConfig`
    needs (one per method and structure mode)."""
    return sorted({step_name(getattr(c.method, "value", c.method), getattr(c.ransac.structure, "value",
                                                                          c.ransac.structure)) for c in configs})


def estimated_seconds(keys: Sequence[str], manifest: Manifest, jobs: int) -> float:
    """About how long compiling ``keys`` on ``jobs`` cores takes: the larger of the CPU seconds
    per core and the longest chain of kernels that wait for each other."""
    keys = [k for k in keys if k in manifest.kernels]
    if not keys:
        return 0.0
    cost = {k: manifest.kernels[k].compile_s for k in keys}
    schedule = _Schedule(kernel_dependencies(keys), cost)
    return max(sum(cost.values()) / max(jobs, 1), max(schedule.chain.values()))


def compile_ahead(steps: Sequence[str], jobs: int | None = None) -> None:
    """Before a command estimates poses: if kernels of ``steps`` are not in numba's cache, say so
    in one line on stderr and compile them on every core (:func:`compile_kernels`).

    Compiling ahead is only a speed-up: with a kernel list that cannot be read (one warning line)
    or a cache that cannot keep kernels (a read-only install without a writable folder: the kernel
    cache says so), nothing is done here and the kernels compile on first use."""
    try:
        manifest = load_manifest()
    except ManifestError as exc:
        logger.warning("%s; kernels compile on first use", exc)
        return
    missing = missing_kernels(manifest.for_steps(steps), manifest)
    if not missing or not _kernels_persist(missing[0]):
        return
    jobs = max(1, int(jobs or os.cpu_count() or 1))
    about = max(10, round(estimated_seconds(missing, manifest, jobs), -1))
    note(f"compiling planarloc's kernels for first use ({len(missing)} kernels, about {about:.0f} s on {jobs} "
         f"core{'s' if jobs > 1 else ''}, once); run `planarloc warmup` at install or image-build time to do it ahead")
    with progress_bar() as update:
        report = compile_kernels(missing, manifest, jobs, update)
    if report.failed:
        logger.info("kernels not compiled ahead (they compile on first use): %s", report.failed)


# ---- the command -----------------------------------------------------------------------------------------
def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "warmup", "compile every numba kernel once, on all cores (run at install or image build time)",
                    """Compile every numba kernel a query uses into numba's on-disk cache: in parallel worker
                    processes (--jobs, default one per core), then by running each estimator once on small
                    generated scenes, which loads them all. The first run on a machine takes about 3 minutes of
                    CPU, spread over the cores; later runs, and queries, only load the cache. Progress goes to stderr (plain
                    lines without a terminal). In a Dockerfile, after pip install:
                    RUN planarloc warmup""",
                    ["planarloc warmup", "planarloc warmup --jobs 8"], run, interrupted=WARMUP_RESUMES)
    p.add_argument("--jobs", "-j", type=int, default=None, help="worker processes (default: one per core)")


def run(args: argparse.Namespace) -> int:
    if args.jobs is not None and args.jobs < 1:
        raise ValueError(f"--jobs: expected an integer >= 1, got {args.jobs}")
    t0 = time.perf_counter()
    manifest = load_manifest()
    missing = missing_kernels(manifest.kernels, manifest)
    if missing and not _kernels_persist(missing[0]):
        raise ValueError("nowhere to keep compiled kernels: planarloc's install is read-only here and neither HOME "
                         "nor the temp folder is writable; run `planarloc warmup` where the install is writable "
                         "(e.g. when the image is built, before USER), or set NUMBA_CACHE_DIR to a writable folder")
    with progress_bar() as update:
        report = compile_kernels(missing, manifest, args.jobs, update)
        times = run_steps(update=update)
    compiled = f"{report.compiled} kernels compiled on {max(1, args.jobs or os.cpu_count() or 1)} cores" \
        if missing else "every listed kernel was cached"
    failed = f", {len(report.failed)} compiled by the steps instead" if report.failed else ""
    slowest = max(times, key=times.get)
    info(f"warm-up done in {time.perf_counter() - t0:.1f} s ({compiled}{failed}; "
         f"slowest step: {slowest}, {times[slowest]:.1f} s)")
    return 0


# ---- writing the kernel list (developers, after changing kernels) ----------------------------------------
def _planarloc_dispatchers() -> dict[str, object]:
    """Every numba dispatcher defined in planarloc's compiled layers, by ``module:qualname``."""
    import pkgutil

    from numba.core.dispatcher import Dispatcher

    out = {}
    for package in ("geometry", "numerics", "solvers", "robust"):
        pkg = importlib.import_module(f"planarloc.{package}")
        for m in pkgutil.iter_modules(pkg.__path__):
            module = importlib.import_module(f"planarloc.{package}.{m.name}")
            for value in vars(module).values():
                if isinstance(value, Dispatcher) and value.py_func.__module__ == module.__name__:
                    out[f"{module.__name__}:{value.py_func.__qualname__}"] = value
    return out


def kernel_cache_files() -> tuple[list[Path], list[Path]]:
    """numba's cache folders of planarloc's kernels, and the index and data files (``*.nbi``,
    ``*.nbc``) of planarloc's modules in them."""
    from planarloc.numerics.kernel_cache import cache_folders

    folders, files = set(), set()
    for d in _planarloc_dispatchers().values():
        cache = getattr(d, "_cache", None)
        if not hasattr(cache, "_cache_file"):  # not a cache=True kernel
            continue
        base = d.py_func.__module__.rpartition(".")[2]
        for path in cache_folders(cache):  # a read-only install: its __pycache__ and this user's folders
            folders.add(Path(path))
            files |= {f for f in Path(path).glob(f"{base}.*") if f.suffix in (".nbi", ".nbc") and f.is_file()
                      and not f.is_symlink()}
    return sorted(folders), sorted(files)


class CompileRecorder:
    """Records numba's compile events (``numba:compile``) while registered: for each planarloc
    kernel compiled (called from Python or from another kernel), the CPU seconds of each
    signature's compilation without the planarloc kernels it compiled on the way (numba's own
    overloads count for the kernel that needed them). Use as a context manager."""

    def __init__(self) -> None:
        self.kernels: dict[str, dict[str, float]] = {}  # module:qualname -> signature repr -> seconds
        self.overloads: dict[str, float] = {}  # numba's own functions compiled for a planarloc kernel -> seconds
        self._stack: list[list] = []
        self._listener = None

    def __enter__(self) -> "CompileRecorder":
        from numba.core import event

        recorder = self

        class Listener(event.Listener):
            def on_start(self, ev: event.Event) -> None:
                recorder._stack.append([ev.data["dispatcher"], ev.data["args"], time.process_time(), 0.0])

            def on_end(self, ev: event.Event) -> None:
                d, sig, t0, inner = recorder._stack.pop()
                total = time.process_time() - t0
                mine = d.py_func.__module__.startswith("planarloc.")
                key = f"{d.py_func.__module__}:{d.py_func.__qualname__}"
                if mine:
                    sigs = recorder.kernels.setdefault(key, {})
                    text = repr(tuple(sig))
                    sigs[text] = sigs.get(text, 0.0) + total - inner
                elif recorder._stack and recorder._stack[-1][0].py_func.__module__.startswith("planarloc."):
                    recorder.overloads[key] = recorder.overloads.get(key, 0.0) + total - inner
                if recorder._stack and mine:
                    recorder._stack[-1][3] += total

        self._listener = Listener()
        event.register("numba:compile", self._listener)
        return self

    def __exit__(self, *exc: object) -> None:
        from numba.core import event

        event.unregister("numba:compile", self._listener)

    def manifest_entries(self) -> dict[str, dict]:
        """``{kernel: {"signatures": [...], "compile_s": seconds}}``, as in ``kernels.json``."""
        return {k: {"signatures": list(sigs), "compile_s": sum(sigs.values())} for k, sigs in self.kernels.items()}


def _profile_steps(out: Path) -> None:
    """Run every step with numba's compile events recorded (:class:`CompileRecorder`)."""
    with CompileRecorder() as rec:
        run_steps()
    out.write_text(json.dumps(rec.manifest_entries()))


def _step_entries(name: str, out: Path) -> None:
    """The kernels a step calls from Python (``Dispatcher.signatures`` of a process that loaded
    them from the cache; the kernels they call are found through :func:`kernel_dependencies`)."""
    run_steps([name])
    out.write_text(json.dumps(sorted(k for k, d in _planarloc_dispatchers().items() if d.signatures)))


def write_manifest(path: Path = MANIFEST) -> None:
    """Regenerate ``kernels.json``: one cold run of all steps in an empty numba cache (every
    kernel's signatures and compile time), then one fresh process per step (the kernels it calls
    from Python)."""
    with tempfile.TemporaryDirectory(prefix="planarloc-kernels-") as tmp:
        env = {**os.environ, "NUMBA_CACHE_DIR": str(Path(tmp) / "cache")}
        me = [sys.executable, "-m", "planarloc.cli.warmup_command"]
        print("compiling every step in an empty cache (minutes) ...", file=sys.stderr, flush=True)
        subprocess.run([*me, "--profile-steps", str(Path(tmp) / "kernels.json")], env=env, check=True)
        kernels = json.loads((Path(tmp) / "kernels.json").read_text())
        steps: dict[str, list[str]] = {}
        for name, _ in warmup_steps():
            print(f"kernels of step {name!r}", file=sys.stderr, flush=True)
            subprocess.run([*me, "--step-entries", name, str(Path(tmp) / "entries.json")], env=env, check=True)
            steps[name] = [k for k in json.loads((Path(tmp) / "entries.json").read_text()) if k in kernels]
    import numba

    for k in kernels.values():
        k["compile_s"] = round(k["compile_s"], 3)
    path.write_text(json.dumps({"numba": numba.__version__, "kernels": dict(sorted(kernels.items())),
                                "steps": steps}, indent=1) + "\n")
    print(f"wrote {path}: {len(kernels)} kernels, {sum(len(k['signatures']) for k in kernels.values())} signatures, "
          f"{sum(k['compile_s'] for k in kernels.values()):.0f} s of compilation", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m planarloc.cli.warmup_command",
                                 description="planarloc's kernel list and compile workers (`planarloc warmup` uses them)")
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--write-manifest", action="store_true", help=f"regenerate {MANIFEST.name} (minutes)")
    g.add_argument("--compile-worker", action="store_true", help=argparse.SUPPRESS)
    g.add_argument("--profile-steps", type=Path, metavar="OUT", help=argparse.SUPPRESS)
    g.add_argument("--step-entries", nargs=2, metavar=("STEP", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.compile_worker:
        return _compile_worker()
    if args.profile_steps:
        _profile_steps(args.profile_steps)
    elif args.step_entries:
        _step_entries(args.step_entries[0], Path(args.step_entries[1]))
    else:
        write_manifest()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
