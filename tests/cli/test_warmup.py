"""`planarloc warmup` and compiling ahead: the kernel list, the parallel compile into an empty
numba cache (real worker processes), the one-line notice, and progress without a terminal."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from _cli_runs import cli, localize_argv
from map_files import map_build_argv

from planarloc.compile import CompileRecorder, load_manifest, warmup_steps
from planarloc.compile.schedule import _Schedule
from planarloc.compile.signatures import parse_signature


def test_the_kernel_list_names_real_cached_kernels_for_every_step() -> None:
    from numba.core.dispatcher import Dispatcher

    from planarloc.compile.dispatchers import dispatcher

    manifest = load_manifest()
    assert set(manifest.steps) == {name for name, _ in warmup_steps()}
    assert all(manifest.steps.values()) and len(manifest.kernels) > 50
    for key, kernel in manifest.kernels.items():
        d = dispatcher(key)
        assert isinstance(d, Dispatcher) and hasattr(d._cache, "_cache_file"), key  # a cache=True kernel
        # every signature parses, literal ones (``Literal[int](5)``: a kernel called with a constant) too
        assert kernel.signatures and all(parse_signature(s) is not None for s in kernel.signatures), key
        assert kernel.compile_s >= 0


def test_a_literal_signature_reads_back_as_the_literal_types_a_constant_argument_compiles() -> None:
    from numba.core import types

    sig = parse_signature(
        "(Array(float64, 2, 'C', False, aligned=True), Literal[int](-1), Literal[bool](True))"
    )
    assert sig == (types.Array(types.float64, 2, "C"), types.literal(-1), types.literal(True))
    assert isinstance(sig[1], types.IntegerLiteral) and sig[1].literal_value == -1
    assert parse_signature("(Literal[int](2**64),)") is None  # an operator: not data


def test_a_kernel_waits_for_the_callees_of_kernels_it_compiles_itself() -> None:
    from planarloc.compile.dispatchers import kernel_dependencies

    batch, essentials = (
        "planarloc.solvers.relpose_5p_nister:_batch",
        "planarloc.solvers.relpose_5p_nister:nister_essentials",
    )
    roots, sturm = (
        "planarloc.solvers.relpose_5p_nister:nister_roots",
        "planarloc.numerics.sturm:real_roots_sturm",
    )
    # the solver kernel is passed to an inlined driver; when it is not handed out itself, the
    # driver's kernel compiles it, so it waits for what the solver calls
    deps = kernel_dependencies([batch, roots, sturm])
    assert deps == {batch: {roots}, roots: {sturm}, sturm: set()}
    deps = kernel_dependencies([batch, essentials, roots, sturm])
    assert deps[batch] == {essentials} and deps[essentials] == {roots}


def test_compile_recorder_times_each_signature_of_planarloc_kernels_only() -> None:
    import numpy as np
    from numba import njit

    from planarloc.geometry import mat3

    dot = njit(mat3.dot.py_func)  # a new dispatcher of a planarloc kernel: nothing compiled yet
    other = njit(lambda a: a[0] + 1.0)  # not planarloc's: recorded only as an overload of a planarloc kernel
    with CompileRecorder() as rec:
        dot(np.ones(3), np.ones(3))
        dot(np.ones(3, dtype=np.int64), np.ones(3, dtype=np.int64))
        other(np.ones(3))
    dot(np.ones(3, dtype=np.float32), np.ones(3, dtype=np.float32))  # after the recorder left: not seen
    sigs = rec.kernels["planarloc.geometry.mat3:dot"]
    assert sorted(sigs) == sorted(repr(tuple(s)) for s in dot.signatures[:2])
    assert all(t > 0 for t in sigs.values())
    assert list(rec.kernels) == ["planarloc.geometry.mat3:dot"]  # the lambda is not planarloc's
    assert not any("lambda" in k for k in rec.overloads)  # nor compiled for a planarloc kernel
    entry = rec.manifest_entries()["planarloc.geometry.mat3:dot"]
    assert entry["signatures"] == list(sigs) and entry["compile_s"] == pytest.approx(sum(sigs.values()))


def test_schedule_hands_out_callees_first_and_the_longest_chain_first() -> None:
    # a <- b <- c (c calls b calls a), d alone, e calls a; costs make a->b->c the long chain
    deps = {"a": set(), "b": {"a"}, "c": {"b"}, "d": set(), "e": {"a"}}
    s = _Schedule(deps, {"a": 1.0, "b": 5.0, "c": 5.0, "d": 3.0, "e": 1.0})
    assert s.take() == "a"  # chain 11 s through b and c, d only 3 s
    assert s.take() == "d"  # b, e wait for a
    got: list[str] = []
    t = threading.Thread(target=lambda: got.append(s.take()))
    t.start()
    s.finish("a")
    t.join(5)
    assert got == ["b"]  # b (chain 10 s) before e (1 s)
    cyclic = _Schedule({"x": {"y"}, "y": {"x"}}, {})
    first = cyclic.take()  # nothing is ready in a call cycle: one is handed out anyway
    cyclic.finish(first)
    assert {first, cyclic.take()} == {"x", "y"}  # and the other once it is compiled
    assert cyclic.take() is None


def _python(code: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=1800)


def test_compile_ahead_says_so_and_fills_an_empty_cache_in_parallel(tmp_path: Path) -> None:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}  # an empty cache: a fresh machine
    ahead = "from planarloc.cli.warmup_command import compile_ahead; compile_ahead(['solvers'], jobs=2)"
    first = _python(ahead, env)
    assert first.returncode == 0, first.stderr
    lines = first.stderr.splitlines()
    notice = [x for x in lines if "for first use" in x]
    assert len(notice) == 1 and re.fullmatch(
        r"compiling planarloc's kernels for first use \(\d+ kernels, about \d+ s on 2 cores, once\); run "
        r"`planarloc warmup` at install or image-build time to do it ahead",
        notice[0],
    )
    assert re.fullmatch(r"compile kernels: 0/\d+ \(0 s\)", lines[1])  # plain progress lines: no terminal here
    assert re.fullmatch(r"compile kernels: (\d+)/\1, done in \d+ s", lines[-1])
    assert sorted((tmp_path / "numba").rglob("*.nbi"))
    # a new process finds everything cached: no notice, and the single-call solvers compile nothing
    check = (
        "from numba.core import event\n"
        "compiled = []\n"
        "class L(event.Listener):\n"
        "    def on_start(self, e): compiled.append(e.data['dispatcher'].py_func.__qualname__)\n"
        "    def on_end(self, e): pass\n"
        "event.register('numba:compile', L())\n"
        f"{ahead}\n"
        "from planarloc.compile import run_steps\n"
        "run_steps(['solvers'])\n"
        "print(compiled)\n"
    )
    second = _python(check, env)
    assert second.returncode == 0, second.stderr
    assert second.stdout.strip() == "[]" and "for first use" not in second.stderr


def test_the_compile_report_times_each_task_and_each_worker(tmp_path: Path) -> None:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    code = (
        "import json\n"
        "from planarloc.compile import compile_kernels, load_manifest\n"
        "keys = ['planarloc.geometry.mat3:sym_eigvals', 'planarloc.numerics.sturm:polyval']\n"
        "r = compile_kernels(keys, load_manifest(), jobs=2)\n"
        "print(json.dumps([r.compiled, r.seconds, r.task_seconds, r.busy_seconds]))\n"
    )
    proc = _python(code, env)
    assert proc.returncode == 0, proc.stderr
    compiled, wall, tasks, busy = json.loads(proc.stdout.strip().splitlines()[-1])
    assert compiled == 2 and sorted(tasks) == [
        "planarloc.geometry.mat3:sym_eigvals",
        "planarloc.numerics.sturm:polyval",
    ]
    assert len(busy) == 2 and all(t > 0 for t in tasks.values())
    assert sum(busy) == pytest.approx(sum(tasks.values())) and max(tasks.values()) <= wall


def test_warmup_without_a_terminal_prints_plain_progress(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "planarloc.cli.main", "warmup"], capture_output=True, text=True, timeout=3600
    )
    assert proc.returncode == 0, proc.stderr
    assert "\x1b[" not in proc.stderr  # no terminal: no bar, no escape codes
    done = [x for x in proc.stderr.splitlines() if x.startswith("run steps: ")]
    assert done[0] == f"run steps: 0/{len(warmup_steps())} (0 s)" and "done in" in done[-1]
    assert re.fullmatch(r"warm-up done in \d+\.\d s \(.*slowest step: .*\)", proc.stdout.strip())


@pytest.mark.parametrize("jobs", ["0", "-2"])
def test_bad_jobs_is_one_line(jobs: str, capsys: pytest.CaptureFixture[str]) -> None:
    from planarloc.cli.main import main

    assert main(["warmup", "--jobs", jobs]) == 1
    assert (
        capsys.readouterr().err.strip()
        == f"planarloc warmup: error: --jobs: expected an integer >= 1, got {jobs}"
    )


# ---- a damaged kernel list ------------------------------------------------------------------------------
BAD_LISTS = {
    "kernels a list": '{"kernels": [], "steps": {}}',
    "not an object": "[1, 2]",
    "signatures a number": (
        '{"kernels": {"planarloc.geometry.mat3:dot": {"signatures": 3, "compile_s": 1}}, "steps": {}}'
    ),
    "steps of numbers": '{"kernels": {}, "steps": {"solvers": [1]}}',
    "not JSON": "{kernels",
}


@pytest.mark.parametrize("text", BAD_LISTS.values(), ids=BAD_LISTS.keys())
def test_load_manifest_names_the_file_and_the_problem(text: str, tmp_path: Path) -> None:
    from planarloc.compile import ManifestError

    bad = tmp_path / "kernels.json"
    bad.write_text(text)
    with pytest.raises(ManifestError) as exc:
        load_manifest(bad)
    assert str(exc.value).startswith(f"{bad}: ") and "\n" not in str(exc.value)


@pytest.fixture(scope="module")
def bad_list_install(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory):
    """This package (with its kernel cache) copied, its kernels.json replaced by one of the wrong
    shape, and a map of the tiny world."""
    import shutil

    import planarloc

    root = tmp_path_factory.mktemp("badlist")
    site = root / "site"
    shutil.copytree(
        Path(planarloc.__file__).parent, site / "planarloc", ignore=shutil.ignore_patterns("*.pyc")
    )
    env = {**os.environ, "PYTHONPATH": str(site)}
    env.pop("NUMBA_CACHE_DIR", None)
    argv = map_build_argv(tiny_world / "map", root / "map.db", "--vocabulary-size", "16")
    built = cli(*argv, env=env, cwd=root, timeout=900)  # cwd: `python -m` puts it first on sys.path
    assert built.returncode == 0, built.stderr
    manifest = site / "planarloc" / "compile" / "kernels.json"
    manifest.write_text(BAD_LISTS["kernels a list"])
    return root, env, manifest


def test_warmup_with_a_kernel_list_of_the_wrong_shape_is_one_line_naming_it(bad_list_install) -> None:
    _root, env, manifest = bad_list_install
    proc = cli("warmup", env=env, cwd=_root, timeout=900)
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 1 and len(err) == 1, proc.stderr
    assert err[0].startswith(
        f"planarloc warmup: error: {manifest}: not planarloc's kernel list ('kernels' must be"
    )


def test_localize_goes_on_without_a_well_formed_kernel_list(bad_list_install, tiny_world: Path) -> None:
    root, env, manifest = bad_list_install
    query = sorted((tiny_world / "query" / "rgb").glob("*.png"))[0]
    cam = (tiny_world / "query" / "camera.txt").read_text().splitlines()[-1]
    proc = cli(
        *localize_argv(root / "map.db", query, "--camera", cam, "--out", "-"), env=env, cwd=root, timeout=900
    )
    assert proc.returncode == 0, proc.stderr
    assert len([x for x in proc.stdout.splitlines() if len(x.split()) == 8]) == 1
    warned = [x for x in proc.stderr.splitlines() if str(manifest) in x]
    assert (
        len(warned) == 1 and warned[0].startswith("WARNING") and "kernels compile on first use" in warned[0]
    )


@pytest.mark.parametrize(
    "text", ["9**9**9**9", "().__class__.__mro__", "[x for x in ()]", "(float64,) * 10**12"]
)
def test_a_signature_in_the_list_is_data_never_code(text: str) -> None:
    assert (
        parse_signature(text) is None
    )  # returns at once: no operator, attribute or comprehension is evaluated


def test_steps_for_names_the_step_of_each_method_and_structure() -> None:
    from planarloc.compile import steps_for
    from planarloc.localize.localizer import LocalizerConfig
    from planarloc.robust.options import RansacOptions

    configs = [LocalizerConfig(method="2p1p", ransac=RansacOptions(structure="none")), LocalizerConfig()]
    assert steps_for(configs) == sorted({"2p1p none", f"{LocalizerConfig().method.value} tracks"})
    assert set(steps_for(configs)) <= {name for name, _ in warmup_steps()}


def test_compile_lazily_plans_nothing_and_ends_with_its_block(monkeypatch: pytest.MonkeyPatch) -> None:
    from planarloc.compile import ahead

    read: list[object] = []
    monkeypatch.setattr(ahead, "load_manifest", lambda: read.append(1) or load_manifest())
    with ahead.compile_lazily():
        assert ahead.plan_ahead(["solvers"]) is None and read == []  # not even the list is read
    ahead.plan_ahead(["solvers"])
    assert read == [1]  # outside the block compiling ahead plans again
