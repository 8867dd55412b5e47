"""A map's gravity: stored at the end of every build, read by every localizer.

The map's gravity (:mod:`planarloc.gravity.world`) is (re)computed at the end of every build that
changed the map from all its poses and stored in the meta keys ``gravity`` (the
:class:`~planarloc.gravity.world.GravityReport` as JSON) and ``world_down`` (the declared or
user-given down direction, if any).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence

import numpy as np

from planarloc.geometry.validation import InputError
from planarloc.gravity.world import GravityReport, WorldDown, gravity_from_map_poses
from planarloc.map.posed_image import PosedImage
from planarloc.map.schema import GRAVITY_META, WORLD_DOWN_META
from planarloc.map.store import MapDatabase

logger = logging.getLogger(__name__)


def declared_world_down(images: Sequence[PosedImage]) -> WorldDown | None:
    """The ``world_down`` the images declare (all must agree), or None if none declares one."""
    found = {im.world_down for im in images if im.world_down is not None}
    if len(found) > 1:
        raise InputError(
            "the images declare different world gravity directions: "
            + "; ".join(f"{w.direction} ({w.detail})" for w in found)
            + "; hint: pass the dataset option up=... for all of them"
        )
    return next(iter(found), None)


def resolve_world_down(
    db: MapDatabase, declared: WorldDown | None
) -> tuple[WorldDown | None, WorldDown | None]:
    """``(stored, to use)`` world down of a map given the new images' declaration (rules in
    :func:`store_map_gravity`); InputError on a contradiction."""
    raw = db.get_meta(WORLD_DOWN_META)
    stored = WorldDown.from_dict(json.loads(raw)) if raw else None
    if declared is None:
        return stored, stored
    if stored is None or declared.source == "option":
        return stored, declared
    if (
        stored.source == "declared"
        and stored.direction is not None  # a declared world down has a direction (WorldDown)
        and declared.direction is not None
        and not np.allclose(stored.direction, declared.direction, atol=1e-9)
    ):
        raise InputError(
            f"{db.path}: the map's world has down = {stored.direction} ({stored.detail}) but the new images "
            f"declare {declared.direction} ({declared.detail}); hint: pass the dataset option up=..."
        )
    return stored, stored


def store_map_gravity(db: MapDatabase, declared: WorldDown | None = None) -> GravityReport:
    """Compute the map's gravity from all its poses and store it (meta ``gravity``).

    Args:
        db: a writable map with at least one image.
        declared: the down direction the images being added declare. A user's ``up=``
            (``source="option"``) replaces what the map stores; a format's declaration must
            agree with a stored one of the same kind, and never replaces a stored option.

    Returns:
        The stored :class:`GravityReport`. Its ``warnings`` are stored with it and logged at INFO
        only: the caller shows them once (`map build` and `map info` in the map's summary,
        `evaluate` before it localizes), never also as a log line.

    Raises:
        InputError: a declaration that contradicts the map's (different world frames).
    """
    stored, use = resolve_world_down(db, declared)
    if use is not None and use != stored:
        db.set_meta(WORLD_DOWN_META, json.dumps(use.to_dict()))
    _, report = gravity_from_map_poses(list(db.load_all_poses().values()), use)
    db.set_meta(GRAVITY_META, json.dumps(report.to_dict()))
    for w in report.warnings:
        logger.info("%s: %s", db.path, w)
    return report


def world_down_changes(db: MapDatabase, declared: WorldDown | None) -> bool:
    """Whether storing the map's gravity with ``declared`` would change the map's world down
    (e.g. a user's ``up=`` given for a map built without it): then its gravity is stored again."""
    stored, use = resolve_world_down(db, declared)
    return use != stored


def map_gravity(db: MapDatabase) -> GravityReport:
    """The map's stored gravity; computed from its poses (not stored) for maps built before it was."""
    raw = db.get_meta(GRAVITY_META)
    if raw:
        return GravityReport.from_dict(json.loads(raw))
    logger.info(
        "%s: the map stores no gravity (built by an older planarloc); estimating it from its poses", db.path
    )
    raw_down = db.get_meta(WORLD_DOWN_META)
    declared = WorldDown.from_dict(json.loads(raw_down)) if raw_down else None
    return gravity_from_map_poses(list(db.load_all_poses().values()), declared)[1]
