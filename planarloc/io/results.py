"""The results of a localize run, written the same way for every path (batch, stream, server).

A run writes two things:

- the **results file** (``--out``): the hloc pose list (:mod:`planarloc.io.pose_list`,
  ``name qw qx qy qz tx ty tz``, ``cam_from_world``) of the queries whose record says
  ``success`` (for a stream: the frames ``localized`` or ``predicted``), written once, when the
  run ends (:meth:`ResultsWriter.close`), by :func:`planarloc.io.output.write_file`: ``-`` is
  standard output, a device or FIFO is written through, a regular file is replaced atomically;
- one **record** per query or frame (:mod:`planarloc.localize.records`), a JSON file in the
  records folder (``--json-dir``; default ``<out>.json.d`` next to a regular results file, none for
  ``-`` or a device), each written atomically as soon as it is known (:func:`record_filename`).

Optionally (``tum``) the successful poses also go to a TUM trajectory (camera-to-world) for evo.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from planarloc.geometry.validation import InputError
from planarloc.io.output import STDOUT, output_kind, write_file
from planarloc.io.pose_list import pose_line
from planarloc.io.tum import tum_lines
from planarloc.localize.records import record_pose


def record_filename(name: str) -> str:
    """File name of a query's record inside the records folder (sub-folders flattened with ``__``)."""
    return name.replace("/", "__") + ".json"


def default_records_dir(out: str | Path) -> Path | None:
    """The records folder of a results file: ``<out>.json.d`` beside a regular file; None for
    ``-`` and for devices or FIFOs (records need ``--json-dir`` there)."""
    if str(out) == STDOUT or output_kind(out) == "through":
        return None
    return Path(out).with_name(Path(out).name + ".json.d")


def query_timestamp(name: str, timestamp: float | None, index: int) -> float:
    """A query's TUM timestamp: its own, else a number in its file name (``1305031102.17.png``,
    ``000012.png``), else its position in the list."""
    if timestamp is not None:
        return float(timestamp)
    m = re.fullmatch(r"(\d+(?:\.\d+)?)", Path(name).stem)
    return float(m.group(1)) if m else float(index)


class ResultsWriter:
    """Collects the records of one run and writes its results (module docstring).

    Args:
        out: the results file, or ``-``.
        records_dir: the records folder, or None for no record files.
        tum: optional TUM trajectory file of the successful poses.

    Use: :meth:`add` per query (in order), then :meth:`close` once (also after an interruption,
    to keep the results so far); a run that fails calls neither, so an earlier results file
    stays as it was.
    """

    def __init__(self, out: str | Path, records_dir: Path | None = None, tum: Path | None = None) -> None:
        self.out = out
        self.records_dir = None if records_dir is None else Path(records_dir)
        self.tum = tum
        self.lines: list[str] = []
        self.statuses: dict[str, int] = {}
        self.names: list[str] = []
        self._tum: list[tuple[float, object]] = []
        if self.records_dir is not None:
            self.records_dir.mkdir(parents=True, exist_ok=True)

    @property
    def queries(self) -> int:
        return len(self.names)

    @property
    def localized(self) -> int:
        return len(self.lines)

    @property
    def errors(self) -> int:
        """Queries that could not be processed (status ``error``)."""
        return self.statuses.get("error", 0)

    def add(self, record: dict, timestamp: float | None = None) -> None:
        """Write one query's record and keep its pose line if it succeeded.

        Raises:
            InputError: a record whose successful pose is not a pose.
            OSError: the record file cannot be written.
        """
        name = str(record["name"])
        try:
            pose = record_pose(record)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{name}: the record's pose is not a pose ({exc})") from None
        if self.records_dir is not None:
            write_file(self.records_dir / record_filename(name), json.dumps(record, indent=1))
        self.names.append(name)
        self.statuses[str(record.get("status"))] = self.statuses.get(str(record.get("status")), 0) + 1
        if pose is not None:
            # The record's own numbers, not a quaternion -> matrix -> quaternion round trip: the
            # results of a served query are byte-identical to a local run's.
            self.lines.append(pose_line(name, [*record["quat_wxyz"], *record["t"]]) + "\n")
            if self.tum is not None:
                self._tum.append((query_timestamp(name, timestamp, len(self.names) - 1), pose))

    def stale_records(self) -> list[str]:
        """Files of the records folder that are not this run's (e.g. of an earlier run)."""
        if self.records_dir is None:
            return []
        ours = {record_filename(n) for n in self.names}
        return sorted(p.name for p in self.records_dir.glob("*.json") if p.name not in ours)

    def close(self) -> None:
        """Write the results file (and the TUM trajectory)."""
        write_file(self.out, "".join(self.lines))
        if self.tum is not None:
            rows = sorted(self._tum, key=lambda r: r[0])
            ts = np.array([t for t, _ in rows])
            if len(ts) > 1 and np.any(np.diff(ts) <= 0):
                raise InputError(f"{self.tum}: two localized queries share a timestamp; TUM files need unique times")
            write_file(self.tum, "".join(["# timestamp tx ty tz qx qy qz qw (camera-to-world)\n",
                                          *tum_lines(ts, [p.inverse() for _, p in rows])]))
