"""The settings a map is built with (stored as ``meta.config``), and what differs between two.

A map stores the configuration it was created with: ``{"features": FeatureConfig as a dict,
"feature_name": ..., "retrieval": {"type": "vlad", "num_words": N}}`` (:func:`map_config`).
Mixing features of two configurations in one map would silently break matching, so a build
into an existing map must use its settings; :func:`settings_mismatch_error` names the keys
that differ. Queries are extracted with the map's features (:func:`feature_config_from_map`).

The feature type (``features.kind``: ``rootsift``, ``xfeat``, ``xfeat-lighterglue``, ``aliked-lightglue``,
:mod:`planarloc.features.registry`) is stored for the learned types only: a map without it was
built with RootSIFT, as every map before learned features was, so their stored configs (and
resuming them) are unchanged. Building into a map of another type names both types.

Caches: :func:`cache_dir` gives the folders where planarloc keeps what it can rebuild: ``evaluate``'s
maps and the images it unpacks from ROS bags (``planarloc cache``). They are this user's, in the temp
folder (``<temp>/planarloc-<uid>/<kind>``, mode 0700), and refused when another user could have
aimed them (a symbolic link, another owner: :mod:`planarloc.numerics.user_folders`).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from planarloc.features.extract import FeatureConfig
from planarloc.features.registry import DEFAULT_FEATURE_TYPE, feature_kind_of_config
from planarloc.geometry.validation import InputError
from planarloc.numerics.user_folders import user_temp_folder

#: The caches planarloc keeps in the temp folder: what each holds.
CACHES = {
    "maps": "maps that `evaluate` builds (and `evaluate --queries` for map sessions); rebuilt when needed",
    "bags": "images unpacked from ROS bags (`--format rosbag` without image_dir); unpacked again when needed",
}


def cache_dir(kind: str, create: bool = True) -> Path:
    """The folder of one of :data:`CACHES`: ``<temp folder>/planarloc-<uid>/<kind>`` (``TMPDIR``),
    this user's own: created with mode 0700 (unless ``create`` is False), and checked at every
    level to be a real folder of this user's that others cannot write to.

    Raises:
        InputError: ``kind`` is not a cache.
        UnsafeFolderError: the folder (or ``planarloc-<uid>``) is a symbolic link, another user's,
            or writable by others (a PermissionError; it is never used then).
        OSError: it cannot be created.
    """
    if kind not in CACHES:
        raise InputError(f"cache: expected one of {', '.join(CACHES)}, got {kind!r}")
    return user_temp_folder(kind, create=create)


def canonical_json(config: Mapping[str, object]) -> str:
    """``config`` as JSON with sorted keys (how it is stored and compared)."""
    if not isinstance(config, Mapping):
        raise InputError(f"config: expected a dict, got {type(config).__name__}")
    try:
        return json.dumps(dict(config), sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise InputError(f"config: must be JSON-serialisable ({exc})") from None


def _flatten(config: Mapping[str, object], prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for k, v in config.items():
        if isinstance(v, Mapping):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def config_diff(stored: Mapping[str, object], given: Mapping[str, object]) -> str:
    """``key: map has X, given Y`` for every differing (nested) key, e.g. ``features.tilt``."""
    a, b = _flatten(stored), _flatten(given)
    diffs = [
        f"{k}: map has {json.dumps(a.get(k))}, given {json.dumps(b.get(k))}"
        for k in sorted(set(a) | set(b))
        if json.dumps(a.get(k)) != json.dumps(b.get(k)) and not k.endswith("feature_name")
    ]
    return "; ".join(diffs) or "feature config differs"


def settings_mismatch_error(
    path: Path, stored: Mapping[str, object], given: Mapping[str, object]
) -> InputError:
    """The error for building into a map made with other settings (names the differing keys, or
    the two feature types when they differ: a map holds one type)."""
    kinds = feature_kind_of_config(dict(stored)), feature_kind_of_config(dict(given))
    if kinds[0] != kinds[1]:
        return InputError(
            f"{path} was built with {kinds[0]} features, not {kinds[1]} (--features): a map holds "
            "one feature type; use a new map file, or --features " + kinds[0]
        )
    return InputError(
        f"{path} was built with another feature config ({config_diff(stored, dict(given))}); use a "
        "new map file, or the map's settings to resume or extend it"
    )


def check_num_words(num_words: object) -> int:
    """The VLAD vocabulary size as an int >= 1 (InputError otherwise)."""
    if isinstance(num_words, bool) or not isinstance(num_words, (int, np.integer)) or num_words < 1:
        raise InputError(f"num_words (--vocabulary-size): expected an integer >= 1, got {num_words!r}")
    return int(num_words)


def map_config(features: FeatureConfig, num_words: int) -> dict:
    """The ``meta.config`` of a map built with these feature and retrieval settings."""
    stored = dataclasses.asdict(features)
    if stored["kind"] == DEFAULT_FEATURE_TYPE:
        del stored["kind"]  # RootSIFT maps read as before (see the module docstring)
    return {
        "features": stored,
        "feature_name": features.name,
        "retrieval": {"type": "vlad", "num_words": int(num_words)},
    }


def feature_config_from_map(db: object) -> FeatureConfig:
    """The FeatureConfig a map (an open :class:`~planarloc.map.store.MapDatabase`) was built with."""
    cfg = dict(db.config.get("features", {}))  # type: ignore[attr-defined]
    cfg.setdefault("resize_max", None)  # maps from before resize_max were extracted at full resolution
    if "tilts" in cfg:
        cfg["tilts"] = tuple(cfg["tilts"])
    return FeatureConfig(**cfg)
