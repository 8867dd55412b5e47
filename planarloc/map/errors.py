"""The map's own lookup error.

A command that asks a map for an image or feature it does not hold gets :class:`MapKeyError`;
the command line turns it into one line with advice (``planarloc map check``). It subclasses
``KeyError`` so existing ``except KeyError`` callers keep working, and it is the only KeyError the
command line explains: any other one is a bug and keeps its traceback.
"""

from __future__ import annotations


class MapKeyError(KeyError):
    """An image (by name or id) or its features are not in the map."""
