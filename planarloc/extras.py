"""Optional dependencies: import them lazily, and name the extra that installs them when missing.

The base install stays light; the service (``planarloc[serve]``) and the Ray backend
(``planarloc[ray]``) import their engines only when used.
"""

from __future__ import annotations

import importlib
from types import ModuleType


class MissingExtraError(ImportError):
    """An optional dependency is not installed; the message names the pip extra."""


def require(module: str, extra: str) -> ModuleType:
    """Import ``module`` or raise :class:`MissingExtraError` naming ``pip install 'planarloc[extra]'``."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtraError(
            f"{module} is not installed ({exc.msg}); install the optional dependencies "
            f"with: pip install 'planarloc[{extra}]'"
        ) from None
