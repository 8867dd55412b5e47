"""Per-image gravity files: one image per line, ``name gx gy gz``.

``(gx, gy, gz)`` is the direction of gravity (pointing down, any non-zero length) in the image's
camera frame (x right, y down, z forward), e.g. an IMU's accelerometer reading at rest, negated
and rotated into the camera frame. ``#`` comment lines and blank lines are ignored; names must
not contain whitespace and must be unique. Example::

    # name gx gy gz
    query/000001.png 0.0 0.996 0.087
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from planarloc.io.lines import iter_named_lines, located
from planarloc.io.text import parse_gravity

FORMAT = "gravity file"
LINE = "'name gx gy gz'"


def read_gravity_file(path: Path) -> dict[str, np.ndarray]:
    """Read a gravity file (format in the module docstring).

    Returns:
        ``{name: (3,) unit gravity direction in that image's camera frame}``, in file order.

    Raises:
        FormatError: missing file, wrong field count, non-numbers, a zero vector or a
            repeated name, naming file and line.
    """
    path = Path(path)
    out: dict[str, np.ndarray] = {}
    for lineno, name, fields in iter_named_lines(Path(path), FORMAT, LINE, 4):
        with located(path, lineno, 2):
            out[name] = parse_gravity(fields)
    return out
