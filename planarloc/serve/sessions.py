"""Fleet sessions: one stream per robot, kept by the service between requests.

A request with the form field ``session`` (an id the robot chooses) is a frame of that robot's
stream: it carries its ``stamp`` (seconds) and optionally its wheel ``odometry``, and is localized
by the session's own :class:`~planarloc.localize.sequence.SequenceLocalizer`. The answer is the
record ``planarloc localize --sequence`` writes per frame
(:func:`planarloc.localize.records.frame_record`: ``status`` ``localized`` / ``predicted`` /
``lost``, ``quat_wxyz`` and ``t`` of ``cam_from_world``, the (6, 6) ``covariance``, ...) plus
``session``: ``{"id", "frame"}``, the frame's number in the stream (1 for the first; a client
that sees it restart knows the stream was restarted).

Two halves:

- :class:`SessionTable`, in the server process: which sessions exist, which worker process
  holds each (a session lives in **one** worker, so its state stays in one process; new sessions
  go to the worker with the fewest), and the bounds: at most ``max_sessions`` sessions (a new one
  evicts the least recently used idle one) and at most ``idle_s`` seconds without an accepted
  frame. Only frames the worker answered count as use: refused ones (4xx) neither keep a session
  alive nor make it recently used, so a client that keeps sending frames the session refuses
  cannot hold it. A session that was evicted or lost (its worker died) answers its next request
  once with **410** and the reason (:class:`SessionGone`); the request after that starts a new
  stream.
- :class:`SessionStates`, in the worker: the session's localizer and its last stamp. Frames of
  one session are run one at a time in arrival order (one worker, one FIFO); a frame whose stamp
  is not after the session's last, or more than :data:`MAX_FRAME_GAP_S` after it, is refused
  (409) and leaves the session unchanged, as does any bad input (4xx; a stamp far ahead of the
  server's clock is refused before the session is looked up,
  :data:`~planarloc.serve.requests.MAX_STAMP_AHEAD_S`). A frame the stream cannot localize
  (black, featureless) is answered with its failure status and the session goes on. A server
  fault while running a frame closes the session (its next request gets 410).

The Ray Serve deployment (:mod:`planarloc.serve.ray_serve`) uses both halves in one replica.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from planarloc.geometry.validation import InputError
from planarloc.localize.localizer import Localizer
from planarloc.localize.records import frame_record
from planarloc.localize.sequence import SequenceConfig, SequenceLocalizer
from planarloc.serve.requests import LocalizeRequest, QuerySettings, RequestError, ServerFault, classify_error
from planarloc.serve.settings import DEFAULT_MAX_SESSIONS, DEFAULT_SESSION_IDLE_S

logger = logging.getLogger(__name__)

#: Forgotten sessions whose reason is kept for their next request, per allowed session (at least 256).
TOMBSTONES_PER_SESSION = 4
#: Largest stamp step from a session's last frame to its next (s). One stamped further ahead (a
#: clock jump, a mistyped stamp) would make every later frame of the stream "out of order": it is
#: refused and the session goes on; a robot whose clock really jumped starts a new session id (or
#: its session is evicted after ``idle_s`` without an accepted frame).
MAX_FRAME_GAP_S = 3600.0


class SessionGone(RequestError):
    """The session's stream state is gone (evicted, or its worker died); HTTP 410, once."""

    def __init__(self, session: str, reason: str) -> None:
        super().__init__(
            410,
            f"session {session!r} {reason}; its stream state is gone: send the frame again to "
            "start a new stream with this id",
        )
        self.session, self.reason = session, reason


@dataclass
class SessionEntry:
    """A session as the server sees it."""

    id: str
    map_name: str
    settings: QuerySettings
    slot: int
    generation: int
    last_used: float  # when it was opened, or its last frame was answered (refused frames do not count)
    pending: int = 0  # frames admitted, not answered yet
    frames: int = 0  # frames answered


@dataclass
class SessionTable:
    """The server's sessions and their bounds (module docstring).

    Args:
        slots: worker processes (a session lives in one).
        max_sessions: sessions kept at once.
        idle_s: seconds without an accepted frame after which a session is evicted.
        clock: monotonic seconds (tests).
    """

    slots: int
    max_sessions: int = DEFAULT_MAX_SESSIONS
    idle_s: float = DEFAULT_SESSION_IDLE_S
    clock: Callable[[], float] = time.monotonic
    entries: OrderedDict[str, SessionEntry] = field(default_factory=OrderedDict)  # least recently used first
    evicted: dict[str, int] = field(default_factory=dict)  # reason kind -> count
    _tombstones: OrderedDict[str, str] = field(default_factory=OrderedDict)
    _generation: int = 0
    _drops: list[SessionEntry] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.max_sessions < 1:
            raise ValueError(f"--max-sessions: must be >= 1, got {self.max_sessions}")
        if not self.idle_s > 0:
            raise ValueError(f"--session-idle: must be > 0 seconds, got {self.idle_s}")

    def _forget(self, entry: SessionEntry, kind: str, reason: str) -> None:
        self.entries.pop(entry.id, None)
        self._tombstones[entry.id] = reason
        self._tombstones.move_to_end(entry.id)
        while len(self._tombstones) > max(256, TOMBSTONES_PER_SESSION * self.max_sessions):
            self._tombstones.popitem(last=False)
        self.evicted[kind] = self.evicted.get(kind, 0) + 1
        self._drops.append(entry)
        logger.info("session %s %s", entry.id, reason)

    def evict_idle(self) -> None:
        """Evict the sessions idle for more than ``idle_s`` (none with a frame in progress)."""
        now = self.clock()
        for entry in list(self.entries.values()):
            if entry.pending == 0 and now - entry.last_used > self.idle_s:
                self._forget(
                    entry,
                    "idle",
                    f"was evicted after {now - entry.last_used:.0f} s without a frame (the "
                    f"server keeps idle sessions for {self.idle_s:g} s)",
                )

    def lose_slot(self, slot: int, reason: str) -> None:
        """Forget every session of a worker whose state is gone (the worker died)."""
        for entry in [e for e in self.entries.values() if e.slot == slot]:
            self._forget(entry, "worker_died", reason)

    def close_after_fault(self, entry: SessionEntry) -> None:
        if self.entries.get(entry.id) is entry:
            self._forget(entry, "fault", "was closed after a server fault in one of its frames")

    def take_drops(self) -> list[SessionEntry]:
        """The sessions forgotten since the last call, whose workers should free their state."""
        drops, self._drops = self._drops, []
        return drops

    def open(self, req: LocalizeRequest, alive: Sequence[bool]) -> SessionEntry:
        """The session of a frame (created if new), with one more frame pending; pair with :meth:`done`.

        Raises:
            SessionGone: the session was evicted or lost since its last frame (once).
            RequestError: 409 for a frame whose map or settings differ from the session's
                first; 503 when all sessions have frames in progress and the table is full.
        """
        assert req.session is not None
        self.evict_idle()
        reason = self._tombstones.pop(req.session, None)
        if reason is not None:
            raise SessionGone(req.session, reason)
        entry = self.entries.get(req.session)
        if entry is not None:
            if (entry.map_name, entry.settings) != (req.map_name, req.settings):
                raise RequestError(
                    409,
                    f"session {req.session!r}: started on map {entry.map_name!r} with "
                    f"{entry.settings}; a frame cannot change them (use "
                    "another session id)",
                )
        else:
            if len(self.entries) >= self.max_sessions:
                idle = [e for e in self.entries.values() if e.pending == 0]
                if not idle:
                    raise RequestError(
                        503,
                        f"{self.max_sessions} sessions are open, all with frames in progress; retry later",
                        retry_after_s=1,
                    )
                self._forget(
                    idle[0],
                    "limit",
                    f"was evicted: {self.max_sessions} sessions were open (the server's "
                    "limit) and it was the least recently used",
                )
            counts = [0] * self.slots
            for e in self.entries.values():
                counts[e.slot] += 1
            candidates = [s for s in range(self.slots) if s < len(alive) and alive[s]] or list(
                range(self.slots)
            )
            slot = min(candidates, key=lambda s: (counts[s], s))
            self._generation += 1
            entry = SessionEntry(
                req.session, req.map_name, req.settings, slot, self._generation, self.clock()
            )
            self.entries[entry.id] = entry
        entry.pending += 1
        return entry

    def done(self, entry: SessionEntry, answered: bool) -> None:
        """A frame of ``entry`` left the server (``answered``: the worker ran it). Only an answered
        frame makes the session recently used (idle time, least recently used order)."""
        entry.pending -= 1
        if answered:
            entry.frames += 1
            entry.last_used = self.clock()
            if self.entries.get(entry.id) is entry:
                self.entries.move_to_end(entry.id)

    @property
    def count(self) -> int:
        return len(self.entries)


@dataclass
class _State:
    generation: int
    sequence: SequenceLocalizer
    last_stamp: float | None = None
    frames: int = 0


class SessionStates:
    """The streams of the sessions a worker holds: ``{session id: SequenceLocalizer}``."""

    def __init__(self) -> None:
        self._states: dict[str, _State] = {}

    def __len__(self) -> int:
        return len(self._states)

    def drop(self, ids: Sequence[str]) -> None:
        for i in ids:
            self._states.pop(i, None)

    def step(self, localizer: Localizer, req: LocalizeRequest, generation: int) -> dict:
        """Localize one frame of ``req.session`` (created, or replaced by a newer ``generation``).

        Returns:
            the frame record plus ``session``: ``{"id", "frame"}``.

        Raises:
            RequestError: 4xx for bad input (the session is unchanged), 409 for a stamp that is
                not after the session's last or more than :data:`MAX_FRAME_GAP_S` after it.
            ServerFault: a fault of the server (the session is dropped).
        """
        sid = str(req.session)
        stamp = req.stamp
        if stamp is None:  # parse_request requires it of a session's frame
            raise RequestError(400, "stamp: required for a frame of a session (seconds)")
        state = self._states.get(sid)
        if state is None or state.generation != generation:
            try:
                config = req.settings.config()
            except InputError as exc:
                raise RequestError(400, str(exc)) from None
            # Each request is answered with its frame's fix (``fixes="wait"``): a served frame has no
            # frame path to keep at camera rate, and its answer is then the CLI's for the same frames.
            state = _State(
                generation, SequenceLocalizer(localizer.with_config(config), SequenceConfig(fixes="wait"))
            )
            self._states[sid] = state
        if state.last_stamp is not None and not stamp > state.last_stamp:
            raise RequestError(
                409,
                f"stamp: {stamp!r} is not after the last frame of session {sid!r} "
                f"({state.last_stamp!r}); send the frames of a session in time order",
            )
        if state.last_stamp is not None and stamp - state.last_stamp > MAX_FRAME_GAP_S:
            raise RequestError(
                409,
                f"stamp: {stamp!r} is {stamp - state.last_stamp:.6g} s after the last "
                f"frame of session {sid!r} ({state.last_stamp!r}), more than "
                f"{MAX_FRAME_GAP_S:g} s; the frame was not used and the session goes on (if "
                "the robot's clock jumped, start a new session id)",
            )
        try:
            estimate = state.sequence.step(
                req.image, req.camera, stamp, odometry=req.odometry, gravity=req.gravity
            )
        except Exception as exc:  # noqa: BLE001 - sorted into the client's and the server's below
            error = classify_error(exc, req.name)
            if isinstance(error, ServerFault):
                self._states.pop(sid, None)
            raise error from None
        state.last_stamp = req.stamp
        state.frames += 1
        return {**frame_record(req.name, estimate), "session": {"id": sid, "frame": state.frames}}
