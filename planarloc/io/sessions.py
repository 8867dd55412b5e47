"""Several recording sessions read as one map (cross-session evaluation, the paper's Sec. V-B).

The paper maps OpenLORIS ``home`` with sessions home1 + home3 and localizes the others. A map
made of several datasets must keep image names unique: with more than one session, every name
is prefixed with its session's label (the folder or bag name, ``home1/color/123.png``); labels
that repeat get ``-2``, ``-3``, ... appended.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from planarloc.geometry.validation import InputError
from planarloc.io.datasets import read_dataset
from planarloc.map.posed_image import PosedImage
from planarloc.map.settings import cache_dir


def session_labels(roots: Sequence[str | Path]) -> list[str]:
    """A unique short label per dataset root (its folder / file stem name)."""
    labels: list[str] = []
    for root in roots:
        p = Path(root)
        base = (p.stem if p.is_file() else p.absolute().name) or "session"
        label, k = base, 2
        while label in labels:
            label, k = f"{base}-{k}", k + 1
        labels.append(label)
    return labels


def read_sessions(roots: Sequence[str | Path], fmt: str, **options: object) -> list[PosedImage]:
    """Read one or more datasets of format ``fmt`` (same options) as one list of posed images.

    Args:
        roots: dataset roots (see :func:`planarloc.io.datasets.read_dataset`).
        fmt: their format.
        **options: reader options applied to every root.

    Returns:
        The images of all roots in order; with 2+ roots, names are ``<label>/<name>``
        (:func:`session_labels`). Indices are kept per session.
    """
    if not roots:
        raise InputError("read_sessions: expected at least one dataset")
    if len(roots) == 1:
        return read_dataset(Path(roots[0]), fmt, **options)
    out: list[PosedImage] = []
    for root, label in zip(roots, session_labels(roots)):
        out += [replace(im, name=f"{label}/{im.name}") for im in read_dataset(Path(root), fmt, **options)]
    return out


def sessions_map_path(roots: Sequence[str | Path], fmt: str, options: dict, feature_name: str) -> Path:
    """Where `evaluate --queries` caches the map of these sessions (temp folder, keyed by
    the resolved roots, the format, its options and the feature settings)."""
    key = "|".join(
        [*(str(Path(r).resolve()) for r in roots), fmt, repr(sorted(options.items())), feature_name]
    )
    digest = hashlib.sha1(key.encode()).hexdigest()[:12]
    name = "+".join(session_labels(roots))[:80]
    return cache_dir("maps") / f"{name}-{digest}.db"
