"""The results of a localize run, written the same way for every path (batch, stream, server).

A run writes two things:

- the **results file** (``--out``): the hloc pose list (:mod:`planarloc.io.pose_list`,
  ``name qw qx qy qz tx ty tz``, ``cam_from_world``) of the queries whose record says
  ``success`` (for a stream: the frames ``localized`` or ``predicted``), written once, when the
  run ends (:meth:`ResultsWriter.close`), by :func:`planarloc.io.output.write_file`: ``-`` is
  standard output, a device or FIFO is written through, a regular file is replaced atomically;
- one **record** per query or frame (:mod:`planarloc.localize.records`), a JSON file in the
  records folder (``--json-dir``; default ``<out>.json.d`` next to a regular results file, none for
  ``-`` or a device) (:func:`record_filename`).

Optionally (``tum``) the successful poses also go to a TUM trajectory (camera-to-world) for evo.

A stream's ``predicted`` frames (a pose the motion model carries, not an absolute fix at the
frame's own time) are marked in both pose files by default (``predicted="mark"``): a comment line
``# predicted <name> position_std_m=<std>`` right before the pose (comment lines are skipped by
planarloc's, hloc's and evo's readers); ``predicted="drop"`` leaves them out of both (the records
keep every frame, with its status).

All of a run's files are replaced together (:class:`planarloc.io.output.StagedFiles`): each record
is written and flushed to a hidden temporary file as soon as it is known, the results file and
the TUM trajectory when the run ends, and only then are all renamed over their targets — the
results file last. A run that fails (a full disk, a server gone, any error) leaves the earlier
results file, trajectory and records exactly as they were (:meth:`ResultsWriter.abort`); a run
that ends or is interrupted (:meth:`ResultsWriter.close`) replaces them.
"""

from __future__ import annotations

import re
from pathlib import Path

from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io import strict_json
from planarloc.io.output import STDOUT, StagedFiles, output_kind, remove_dead_temporaries
from planarloc.io.pose_list import pose_line
from planarloc.io.tum import tum_trajectory_text

#: what the pose files do with a stream's ``predicted`` frames (module docstring)
PREDICTED_MODES = ("mark", "drop")
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
        predicted: ``"mark"`` or ``"drop"`` a stream's predicted frames in the pose files.

    Use: :meth:`add` per query (in order), then :meth:`close` once (also after an interruption,
    to keep the results so far); a run that fails calls :meth:`abort` (or neither), so the
    earlier results file and records stay as they were. As a context manager, an exception
    aborts.
    """

    def __init__(
        self,
        out: str | Path,
        records_dir: Path | None = None,
        tum: Path | None = None,
        predicted: str = "mark",
    ) -> None:
        if predicted not in PREDICTED_MODES:
            raise InputError(f"predicted: expected one of {PREDICTED_MODES}, got {predicted!r}")
        self.predicted = predicted
        self.out = out
        self.records_dir = None if records_dir is None else Path(records_dir)
        self.tum = tum
        self.lines: list[str] = []
        self.statuses: dict[str, int] = {}
        self.names: list[str] = []
        self._tum: list[tuple[float, Pose, str | None]] = []  # stamp, pose, the predicted mark
        self._staged = StagedFiles()
        if self.records_dir is not None:
            self.records_dir.mkdir(parents=True, exist_ok=True)
            remove_dead_temporaries(self.records_dir)

    def __enter__(self) -> ResultsWriter:
        return self

    def __exit__(self, kind: object, *_: object) -> None:
        if kind is not None:
            self.abort()

    @property
    def queries(self) -> int:
        return len(self.names)

    @property
    def localized(self) -> int:
        """Poses written to the results file."""
        return sum(not line.startswith("#") for line in self.lines)

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
            self._staged.add(self.records_dir / record_filename(name), strict_json.dumps(record, indent=1))
        self.names.append(name)
        self.statuses[str(record.get("status"))] = self.statuses.get(str(record.get("status")), 0) + 1
        mark = None
        if pose is not None and record.get("status") == "predicted":
            if self.predicted == "drop":
                return
            std = record.get("position_std_m")
            mark = f"# predicted {name} position_std_m={'null' if std is None else f'{float(std):.4f}'}\n"
        if pose is not None:
            # The record's own numbers, not a quaternion -> matrix -> quaternion round trip: the
            # results of a served query are byte-identical to a local run's.
            if mark is not None:
                self.lines.append(mark)
            self.lines.append(pose_line(name, [*record["quat_wxyz"], *record["t"]]) + "\n")
            if self.tum is not None:
                self._tum.append((query_timestamp(name, timestamp, len(self.names) - 1), pose, mark))

    def stale_records(self) -> list[str]:
        """Files of the records folder that are not this run's (e.g. of an earlier run)."""
        if self.records_dir is None:
            return []
        ours = {record_filename(n) for n in self.names}
        return sorted(
            p.name
            for p in self.records_dir.glob("*.json")
            if p.name not in ours and not p.name.startswith(".")
        )

    def close(self) -> None:
        """Replace the results file, the TUM trajectory and the records, together (module docstring).

        Raises:
            InputError: the TUM trajectory would have two poses at one time (nothing is replaced).
            OSError: a file cannot be written, e.g. a full disk (nothing is replaced).
        """
        try:
            if self.tum is not None:
                rows = sorted(self._tum, key=lambda r: r[0])
                text = tum_trajectory_text(self.tum, [r[0] for r in rows], [r[1].inverse() for r in rows])
                head, *body = text.splitlines(keepends=True)
                self._staged.add(self.tum, head + "".join((r[2] or "") + line for r, line in zip(rows, body)))
            self._staged.add(self.out, "".join(self.lines))
        except BaseException:
            self.abort()
            raise
        self._staged.commit()

    def abort(self) -> None:
        """Drop this run's files: the earlier ones stay as they were."""
        self._staged.discard()
