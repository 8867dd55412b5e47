"""Compiling planarloc's numba kernels ahead, into numba's on-disk cache, on all cores.

numba compiles a kernel on its first call and caches the machine code next to its module
(``__pycache__/*.nbi, *.nbc``; :mod:`planarloc.numerics.kernel_cache`). Compiling all of
planarloc's kernels takes about 170 s of CPU, so ``planarloc warmup`` does it once at install or
image-build time. Without it, ``planarloc localize``, the ROS 2 node and the service's workers
run the kernels as Python while a detached process compiles them (:mod:`.first_use`; the
service's workers share one), and the other commands call :func:`compile_ahead` before
estimating poses.

- :mod:`.manifest`: the shipped kernel list ``kernels.json`` (kernels, signatures, compile
  seconds, the kernels of each warm-up step); :mod:`.signatures` reads its signatures as data.
- :mod:`.dispatchers`: planarloc's numba dispatchers and the kernels each calls.
- :mod:`.cache`: the kernels numba's cache misses, and its files.
- :mod:`.steps`: the warm-up steps, small runs that call every kernel a query uses.
- :mod:`.schedule`: compiling kernels in worker processes, callees first, longest chain first.
- :mod:`.ahead`: :func:`compile_ahead`, what the front doors call (:func:`compile_lazily` to skip it).
- :mod:`.interpreted`: the kernels run as plain Python (except a few hot ones) while they compile.
- :mod:`.background`: compiling in a detached process, one per kernel cache (a lock file).
- :mod:`.first_use`: the two together, a first pose in seconds on an empty cache (``planarloc
  localize``, the node, the service's workers).
- :mod:`.recorder`: :class:`CompileRecorder`, numba's compile events per kernel and signature.
- ``python -m planarloc.compile --write-manifest`` regenerates the list after kernels change.
"""

from planarloc.compile.ahead import AheadPlan, compile_ahead, compile_lazily, plan_ahead
from planarloc.compile.cache import kernel_cache_files, missing_kernels
from planarloc.compile.manifest import MANIFEST, Kernel, Manifest, ManifestError, load_manifest
from planarloc.compile.recorder import CompileRecorder
from planarloc.compile.schedule import COMPILE_STAGE, CompileReport, compile_kernels
from planarloc.compile.steps import STEPS_STAGE, run_steps, steps_for, warmup_steps

__all__ = [
    "COMPILE_STAGE",
    "MANIFEST",
    "STEPS_STAGE",
    "AheadPlan",
    "CompileRecorder",
    "CompileReport",
    "Kernel",
    "Manifest",
    "ManifestError",
    "compile_ahead",
    "compile_kernels",
    "compile_lazily",
    "kernel_cache_files",
    "load_manifest",
    "missing_kernels",
    "plan_ahead",
    "run_steps",
    "steps_for",
    "warmup_steps",
]
