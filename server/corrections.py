"""Corrections back to the robots: each anchored session's ``T_map_odom``, published and queryable.

:class:`CorrectionPublisher` is the server's one sender of
:class:`~wardmap.shared.robotwire.CorrectionMsg` (schema ``wardmap.correction``, docs/wire.md).
On the server's one zenoh session (opened and closed by the composition root) it

- declares, per robot and on first use, a publisher on ``wardmap/v1/robots/<robot_id>/correction``
  (:func:`~wardmap.shared.zenoh_config.correction_key`), reliable with congestion control
  ``BLOCK``, and puts every correction :meth:`CorrectionPublisher.publish` is given;
- keeps the latest correction of every ``(robot, session)`` in memory, and answers queries on
  :data:`~wardmap.shared.zenoh_config.ALL_CORRECTIONS` (``wardmap/v1/robots/*/correction``) with
  it, so a robot that (re)connects, or missed a put, learns its correction:
  ``wardmap/v1/robots/<id>/correction?session_id=<sid>`` gets that session's latest (no reply
  when there is none); without ``session_id``, the robot's most recently published one; a
  wildcard key one reply per matching robot. A bad ``session_id`` gets a reply error.

Threads: :meth:`~CorrectionPublisher.publish` may be called from any thread (the back-end's
worker); a lock guards the latest corrections, and a second lock is held while a put is in
flight so :meth:`~CorrectionPublisher.close` never undeclares a publisher under it. Queries reach
one worker thread through a bounded zenoh FIFO channel (``FifoChannel(capacity)``): **FIFO, block
when full** (zenoh applies backpressure, nothing is dropped).

The latest corrections live in memory only: after a restart the back-end publishes each anchored
session's correction again (with a revision above the one robots hold, see ``publish``).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike

from wardmap.server.store import SessionAnchor
from wardmap.server.zenoh_session import first_line
from wardmap.shared.errors import ConfigError, WardmapError, WireError
from wardmap.shared.robotwire import ENCODING, CorrectionMsg, encode_correction
from wardmap.shared.wire import check_id
from wardmap.shared.zenoh_config import ALL_CORRECTIONS, correction_key

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_CAPACITY",
    "CorrectionCounters",
    "CorrectionError",
    "CorrectionPublisher",
]

DEFAULT_CAPACITY: Final = 64
"""Queries the zenoh FIFO channel holds before zenoh applies backpressure."""
SESSION_PARAM: Final = "session_id"
"""Selector parameter that asks for one session's correction."""


class CorrectionError(WardmapError):
    """A correction cannot be published: the publisher is closed, the revision does not increase,
    or zenoh refuses a declaration."""


@dataclass(frozen=True, slots=True)
class CorrectionCounters:
    """Counts since construction.

    Attributes:
        published: corrections put on zenoh.
        publish_failures: corrections zenoh refused to put (logged; still answered to queries).
        queries: queries answered (with or without a correction).
        query_errors: queries answered with a reply error (bad ``session_id``).
    """

    published: int
    publish_failures: int
    queries: int
    query_errors: int


class CorrectionPublisher:
    """Publish robot sessions' corrections and answer queries for the latest; see the module
    docstring. Use ``close()`` or a ``with`` block."""

    def __init__(self, session: Any, *, capacity: int = DEFAULT_CAPACITY,
                 clock: Callable[[], float] = time.time) -> None:
        """Declare the queryable and start its worker.

        Args:
            session: the process's open ``zenoh.Session``; it must outlive :meth:`close`
                (its owner closes it after).
            capacity: size of the queryable's FIFO channel (>= 1).
            clock: Unix time in seconds, the corrections' ``stamp``.

        Raises:
            ConfigError: a bad capacity.
            CorrectionError: zenoh refuses the queryable (e.g. the session is closed).
        """
        import zenoh

        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise ConfigError(f"correction publisher capacity must be an int >= 1, got {capacity!r}")
        self._session = session
        self._clock = clock
        self._lock = threading.Lock()  # guards _latest, _recent and _counts
        self._latest: dict[tuple[str, str], tuple[CorrectionMsg, bytes]] = {}
        self._recent: dict[str, str] = {}  # robot -> its session whose correction came last
        self._counts = {"published": 0, "publish_failures": 0, "queries": 0, "query_errors": 0}
        self._publish_lock = threading.Lock()  # held while a put is in flight; guards _publishers
        self._publishers: dict[str, Any] = {}
        self._closed = False
        try:
            self._queryable: Any = session.declare_queryable(
                ALL_CORRECTIONS, zenoh.handlers.FifoChannel(capacity)
            )
        except zenoh.ZError as exc:
            raise CorrectionError(
                f"cannot declare the queryable {ALL_CORRECTIONS}: {first_line(exc)}"
            ) from exc
        # The worker reads the channel: undeclaring the queryable closes it, and recv() then
        # ends once the channel is empty.
        self._thread: threading.Thread | None = threading.Thread(
            target=self._run, args=(self._queryable.handler,), name="wardmap-corrections", daemon=True
        )
        self._thread.start()
        log.info("corrections: queryable %s", ALL_CORRECTIONS)

    # ------------------------------------------------------------------ publishing

    def publish(
        self,
        robot_id: str,
        session_id: str,
        T_map_odom: ArrayLike,
        *,
        revision: int,
        anchored_to: str | None = None,
    ) -> CorrectionMsg:
        """Publish a session's new ``T_map_odom`` and keep it as the session's latest.

        Args:
            robot_id, session_id: the robot session whose ``odom`` frame is corrected.
            T_map_odom: (4, 4) rigid transform, the session's odom frame in the map frame.
            revision: higher than every revision published for this session before (robots
                refuse lower ones as ``stale``); after a server restart, higher than any a
                robot may still hold (persist it with the pose graph).
            anchored_to: ``"<robot_id>/<session_id>"`` of the map session the anchoring closure
                reached, or None.

        Returns:
            The message sent (``stamp`` = now, ``state`` = ``anchored``).

        Raises:
            WireError: a bad id, revision, pose or ``anchored_to`` (names the field).
            CorrectionError: closed, or ``revision`` not above the session's latest.

        A put zenoh refuses is logged and counted (``publish_failures``); the correction is
        still the session's latest, answered to queries (robots query periodically).
        """
        import zenoh

        msg = CorrectionMsg(robot_id, session_id, revision, self._clock(), np.asarray(T_map_odom, np.float64),
                            "anchored", anchored_to)
        payload = encode_correction(msg)
        with self._lock:
            if self._closed:
                raise CorrectionError("the correction publisher is closed")
            held = self._latest.get((robot_id, session_id))
            if held is not None and held[0].revision >= msg.revision:
                raise CorrectionError(f"correction of {robot_id}/{session_id}: revision {msg.revision} "
                                      f"does not increase (latest {held[0].revision})")
            self._latest[(robot_id, session_id)] = (msg, payload)
            self._recent[robot_id] = session_id
        with self._publish_lock:
            try:
                publisher = self._publishers.get(robot_id)
                if publisher is None:
                    if self._closed:
                        raise CorrectionError("the correction publisher is closed")
                    publisher = self._session.declare_publisher(
                        correction_key(robot_id),
                        encoding=ENCODING,
                        reliability=zenoh.Reliability.RELIABLE,
                        congestion_control=zenoh.CongestionControl.BLOCK,
                    )
                    self._publishers[robot_id] = publisher
                publisher.put(payload)
            except zenoh.ZError as exc:
                self._count("publish_failures")
                log.warning("cannot publish the correction of %s/%s (revision %d): %s",
                            robot_id, session_id, msg.revision, first_line(exc))
                return msg
        self._count("published")
        log.info("correction of %s/%s revision %d published (anchored to %s)",
                 robot_id, session_id, msg.revision, anchored_to or "-")
        return msg

    def publish_anchor(self, anchor: SessionAnchor) -> CorrectionMsg | None:
        """Publish a session's anchoring as the back-end committed it (None: not anchored)."""
        if anchor.T_map_odom is None:
            return None
        return self.publish(anchor.robot_id, anchor.session_id, anchor.T_map_odom, revision=anchor.revision,
                            anchored_to=anchor.anchored_to or None)

    def load(self, anchors: Iterable[SessionAnchor]) -> None:
        """Hold the stored anchored sessions as their latest corrections, without publishing them
        (a restarted server answers queries with what robots may already hold)."""
        for a in anchors:
            if a.T_map_odom is None:
                continue
            msg = CorrectionMsg(a.robot_id, a.session_id, a.revision, self._clock(),
                                np.asarray(a.T_map_odom, np.float64), "anchored", a.anchored_to or None)
            with self._lock:
                self._latest[(a.robot_id, a.session_id)] = (msg, encode_correction(msg))
                self._recent[a.robot_id] = a.session_id

    def latest(self, robot_id: str, session_id: str | None = None) -> CorrectionMsg | None:
        """The latest correction of ``robot_id``'s session ``session_id`` (default: of the
        session published last), or None."""
        with self._lock:
            sid = self._recent.get(robot_id) if session_id is None else session_id
            held = None if sid is None else self._latest.get((robot_id, sid))
        return None if held is None else held[0]

    def counters(self) -> CorrectionCounters:
        """The counters now (consistent snapshot)."""
        with self._lock:
            c = dict(self._counts)
        return CorrectionCounters(c["published"], c["publish_failures"], c["queries"], c["query_errors"])

    # ------------------------------------------------------------------ life cycle

    def close(self, timeout_s: float = 10.0) -> None:
        """Undeclare the publishers and the queryable, join the worker (idempotent). The
        session stays open; its owner closes it."""
        with self._lock:
            self._closed = True
        with self._publish_lock:  # waits for a put in flight
            publishers, self._publishers = self._publishers, {}
        for publisher in publishers.values():
            publisher.undeclare()
        queryable, self._queryable = self._queryable, None
        if queryable is not None:
            queryable.undeclare()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout_s)
            if thread.is_alive():
                log.warning("correction query worker did not stop within %.1f s", timeout_s)

    def __enter__(self) -> CorrectionPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ queries

    def _count(self, name: str) -> None:
        with self._lock:
            self._counts[name] += 1

    def _run(self, queries: Any) -> None:
        import zenoh

        while True:
            try:
                query = queries.recv()  # raises ZError once the channel is closed and empty
            except zenoh.ZError:
                break
            with query:  # the final reply is sent when the query is dropped
                try:
                    self._answer(query)
                except Exception:
                    log.exception("correction query %s failed", str(query.selector)[:200])
        log.debug("correction query worker ends")

    def _answer(self, query: Any) -> None:
        import zenoh

        session_id: str | None = None
        for key, value in query.parameters:
            if str(key) == SESSION_PARAM:
                try:
                    session_id = check_id(str(value), SESSION_PARAM)
                except WireError as exc:
                    self._count("query_errors")
                    query.reply_err(str(exc)[:300].encode())
                    return
        asked = zenoh.KeyExpr(str(query.key_expr))
        with self._lock:
            robots = sorted(self._recent)
            answers = []
            for robot_id in robots:
                key = correction_key(robot_id)
                if not asked.intersects(zenoh.KeyExpr(key)):
                    continue
                sid = self._recent[robot_id] if session_id is None else session_id
                held = self._latest.get((robot_id, sid))
                if held is not None:
                    answers.append((key, held[1]))
        for key, payload in answers:
            query.reply(key, payload, encoding=ENCODING)
        self._count("queries")
