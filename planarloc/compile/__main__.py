"""``python -m planarloc.compile``: regenerate the kernel list (developers, after changing
kernels: ``--write-manifest``, minutes), the compile worker processes of :mod:`.schedule`, and
the detached compile of :mod:`.background` (``--background STEP...``)."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from planarloc.compile.background import run_background_compile
from planarloc.compile.dispatchers import planarloc_dispatchers
from planarloc.compile.manifest import MANIFEST
from planarloc.compile.recorder import CompileRecorder
from planarloc.compile.schedule import serve_compile_requests
from planarloc.compile.steps import run_steps, warmup_steps

ME = (sys.executable, "-m", "planarloc.compile")


def _profile_steps(out: Path) -> None:
    """Run every step with numba's compile events recorded (:class:`CompileRecorder`)."""
    with CompileRecorder() as rec:
        run_steps()
    out.write_text(json.dumps(rec.manifest_entries()))


def _step_entries(name: str, out: Path) -> None:
    """The kernels a step calls from Python (``Dispatcher.signatures`` of a process that loaded
    them from the cache; the kernels they call are found through their bytecode)."""
    run_steps([name])
    out.write_text(json.dumps(sorted(k for k, d in planarloc_dispatchers().items() if d.signatures)))


def write_manifest(path: Path = MANIFEST) -> None:
    """Regenerate ``kernels.json``: one cold run of all steps in an empty numba cache (every
    kernel's signatures and compile time), then one fresh process per step (the kernels it calls
    from Python)."""
    with tempfile.TemporaryDirectory(prefix="planarloc-kernels-") as tmp:
        env = {**os.environ, "NUMBA_CACHE_DIR": str(Path(tmp) / "cache")}
        print("compiling every step in an empty cache (minutes) ...", file=sys.stderr, flush=True)
        subprocess.run([*ME, "--profile-steps", str(Path(tmp) / "kernels.json")], env=env, check=True)
        kernels = json.loads((Path(tmp) / "kernels.json").read_text())
        steps: dict[str, list[str]] = {}
        for name, _ in warmup_steps():
            print(f"kernels of step {name!r}", file=sys.stderr, flush=True)
            subprocess.run(
                [*ME, "--step-entries", name, str(Path(tmp) / "entries.json")], env=env, check=True
            )
            steps[name] = [k for k in json.loads((Path(tmp) / "entries.json").read_text()) if k in kernels]
    import numba

    for k in kernels.values():
        k["compile_s"] = round(k["compile_s"], 3)
    path.write_text(
        json.dumps(
            {"numba": numba.__version__, "kernels": dict(sorted(kernels.items())), "steps": steps}, indent=1
        )
        + "\n"
    )
    print(
        f"wrote {path}: {len(kernels)} kernels, {sum(len(k['signatures']) for k in kernels.values())} "
        f"signatures, {sum(k['compile_s'] for k in kernels.values()):.0f} s of compilation",
        file=sys.stderr,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m planarloc.compile",
        description="planarloc's kernel list and compile workers (`planarloc warmup` uses them)",
    )
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--write-manifest", action="store_true", help=f"regenerate {MANIFEST.name} (minutes)")
    g.add_argument("--compile-worker", action="store_true", help=argparse.SUPPRESS)
    g.add_argument("--profile-steps", type=Path, metavar="OUT", help=argparse.SUPPRESS)
    g.add_argument("--step-entries", nargs=2, metavar=("STEP", "OUT"), help=argparse.SUPPRESS)
    g.add_argument("--background", nargs="+", metavar="STEP", help=argparse.SUPPRESS)
    ap.add_argument("--jobs", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.background:
        return run_background_compile(args.background, max(1, args.jobs))
    if args.compile_worker:
        serve_compile_requests(sys.stdin, sys.stdout)
    elif args.profile_steps:
        _profile_steps(args.profile_steps)
    elif args.step_entries:
        _step_entries(args.step_entries[0], Path(args.step_entries[1]))
    else:
        write_manifest()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
