"""What :class:`~planarloc.map.store.MapDatabase` holds, declared once for the type checker.

Its reading and writing halves (:mod:`planarloc.map.store_read`, :mod:`planarloc.map.store_write`)
are mixins over the same connection and caches; :class:`MapState` names them for both. Nothing
here exists at run time: ``MapDatabase.__init__`` sets the attributes.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import sqlite3
    from collections import OrderedDict
    from pathlib import Path

    from planarloc.features.extract import Features
    from planarloc.geometry.camera import Camera
    from planarloc.geometry.pose import Pose
    from planarloc.map.codec import DescriptorBasis


class MapState:
    """The attributes and shared helpers of a :class:`~planarloc.map.store.MapDatabase`."""

    if TYPE_CHECKING:
        path: Path
        _cache: OrderedDict[int, Features]
        _cache_size: int
        _cameras: dict[int, Camera]
        _camera_ids: dict[tuple, int]
        _kp_layout: str
        _dim: int | None
        _encoding: str
        _global_encoding: str
        _storage: str
        _sources: bool | None
        _basis: DescriptorBasis | None
        _poses: tuple[tuple[int, int], dict[int, Pose]] | None

        @property
        def _db(self) -> sqlite3.Connection: ...
        def _resolve_id(self, key: str | int) -> int: ...
