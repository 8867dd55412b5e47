"""Python code run in a fresh interpreter (nothing this test process imported is loaded there)."""

from __future__ import annotations

import subprocess
import sys


def python_stdout(code: str, timeout: float) -> str:
    """Runs ``code`` with ``python -c``, which must succeed (its stderr is the failure message), and
    returns what it printed; ``timeout`` in s."""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout
