"""OpenBLAS's idle-thread spin: set before numpy loads, the user's choice kept."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from planarloc.numerics.blas_threads import OPENBLAS_IDLE_TIMEOUT, shorten_openblas_spin

# Records OPENBLAS_THREAD_TIMEOUT as it is when numpy (and with it OpenBLAS) starts loading.
_PROBE = """
import importlib.abc, os, sys
seen = []
class Probe(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "numpy" and not seen:
            seen.append(os.environ.get("OPENBLAS_THREAD_TIMEOUT"))
        return None
sys.meta_path.insert(0, Probe())
import planarloc
print(seen[0] if seen else "numpy never imported", os.environ.get("OPENBLAS_THREAD_TIMEOUT"))
"""


def _probe(**env: str) -> list[str]:
    clean = {
        k: v for k, v in os.environ.items() if k not in ("OPENBLAS_THREAD_TIMEOUT", "GOTO_THREAD_TIMEOUT")
    }
    done = subprocess.run(
        [sys.executable, "-c", _PROBE], env={**clean, **env}, capture_output=True, text=True, check=True
    )
    return done.stdout.split()


def test_import_sets_the_timeout_before_numpy_loads():
    """``import planarloc`` sets it before its first numpy import, where OpenBLAS reads it."""
    assert _probe() == [str(OPENBLAS_IDLE_TIMEOUT)] * 2


@pytest.mark.parametrize("name", ["OPENBLAS_THREAD_TIMEOUT", "GOTO_THREAD_TIMEOUT"])
def test_a_value_the_user_set_is_kept(name):
    at_numpy, after = _probe(**{name: "8"})
    assert after == ("8" if name == "OPENBLAS_THREAD_TIMEOUT" else "None")
    assert at_numpy == after


def test_after_numpy_it_is_set_for_child_processes_only():
    """With numpy already loaded (as in this process) the setting cannot reach this process's
    OpenBLAS: said by the result; child processes still inherit it."""
    env: dict[str, str] = {}
    assert "numpy" in sys.modules
    assert shorten_openblas_spin(env) is False
    assert env == {"OPENBLAS_THREAD_TIMEOUT": str(OPENBLAS_IDLE_TIMEOUT)}
    user = {"OPENBLAS_THREAD_TIMEOUT": "6"}
    assert shorten_openblas_spin(user) is False and user == {"OPENBLAS_THREAD_TIMEOUT": "6"}
