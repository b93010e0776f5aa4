"""Keyframe ingest: zenoh subscriber -> decode + validate -> store -> ack.

:class:`Ingest` declares, on the server's one zenoh session (opened and closed by the
composition root, ``server/app.py``), one subscriber on
:data:`~wardmap.shared.zenoh_config.ALL_KEYFRAMES` and one ack publisher per robot, and runs
one worker thread. Samples reach the worker through a bounded zenoh FIFO channel
(``zenoh.handlers.FifoChannel``). :meth:`Ingest.stop` undeclares all of them; the session
outlives it.

Queue policy: **FIFO, block when full (backpressure, never drop)**. When the channel holds
``capacity`` samples, zenoh stops taking samples off the transport; the robots publish
reliable with congestion control ``BLOCK``, so their puts wait instead of being dropped.

For each sample the worker decodes the keyframe, checks that the robot id in the key equals
the message's ``robot_id``, stores it and only *after* the insert committed publishes an
:class:`~wardmap.shared.wire.AckMsg` (``stored`` or ``duplicate``) on
:func:`~wardmap.shared.zenoh_config.ack_key`. Bad input never stops the worker: a
:class:`~wardmap.shared.errors.WardmapError` is counted as a rejection in the store (and
acked ``rejected`` when the robot is known); an unexpected exception is logged with the
payload size and counted as ``internal``.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Any, Final

from wardmap.server.store import KeyframeStore
from wardmap.server.zenoh_session import first_line
from wardmap.shared.errors import ConfigError, WardmapError, WireError
from wardmap.shared.wire import AckMsg, AckStatus, KeyframeMsg, decode_keyframe, encode
from wardmap.shared.zenoh_config import ALL_KEYFRAMES, ack_key, robot_id_from_key

log = logging.getLogger(__name__)

# Rejection reasons name a top-level keyframe field, never a name taken from the payload:
# otherwise a publisher could mint unlimited reasons (database rows, Prometheus labels).
_KNOWN_FIELDS = frozenset({f.name for f in dataclasses.fields(KeyframeMsg)} | {"schema", "version"})


def wire_reason(field: str) -> str:
    """A bounded rejection reason for a WireError on ``field``: ``keypoints.uv`` -> ``wire: keypoints``."""
    top = field.split(".", 1)[0].split("[", 1)[0]
    if not top:
        return "wire: payload"
    return f"wire: {top}" if top in _KNOWN_FIELDS else "wire: unknown field"

__all__ = ["DEFAULT_CAPACITY", "Ingest", "IngestCounters", "IngestError"]

DEFAULT_CAPACITY: Final = 256
"""Samples the zenoh FIFO channel holds before zenoh applies backpressure."""
MAX_ACK_PUBLISHERS: Final = 1024
"""Ack publishers kept declared (one per robot); the least recently used is undeclared beyond this."""
_MAX_REASON: Final = 200


class IngestError(WardmapError):
    """The ingest cannot start (already started, zenoh refuses the subscriber)."""


@dataclass(frozen=True, slots=True)
class IngestCounters:
    """A snapshot of the ingest's counters since :meth:`Ingest.start`.

    Attributes:
        received: samples taken from the channel.
        stored: keyframes newly stored (and acked ``stored``).
        duplicates: keyframes already stored (acked ``duplicate``).
        rejected: samples rejected (bad payload, key/robot mismatch, store error, internal).
        queue_depth: samples the worker has taken from the zenoh channel and not yet
            processed (a lower bound of the backlog: zenoh does not expose its channel's length).
        ack_failures: acks that could not be published.
    """

    received: int
    stored: int
    duplicates: int
    rejected: int
    queue_depth: int
    ack_failures: int


class Ingest:
    """Subscribe to every robot's keyframes, store them and ack them; see the module docstring.

    Use ``start()`` / ``stop()`` or a ``with`` block. Thread safety: :meth:`counters` may be
    called from any thread; everything else from the owning thread.
    """

    def __init__(
        self,
        session: Any,
        store: KeyframeStore,
        *,
        capacity: int = DEFAULT_CAPACITY,
        clock: Any = time.time,
    ) -> None:
        """
        Args:
            session: the process's open ``zenoh.Session``; it must outlive this object's
                ``stop()`` (its owner closes it after).
            store: where keyframes go; it must outlive this object's ``stop()``.
            capacity: size of the zenoh FIFO channel (>= 1).
            clock: wall-clock seconds for ``received_s`` (``time.time``).
        """
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise ConfigError(f"ingest capacity must be an int >= 1, got {capacity!r}")
        self._session = session
        self._store = store
        self._capacity = capacity
        self._clock = clock
        self._lock = threading.Lock()
        self._counts = {"received": 0, "stored": 0, "duplicates": 0, "rejected": 0, "ack_failures": 0}
        self._backlog: deque[Any] = deque()
        self._subscriber: Any = None
        self._thread: threading.Thread | None = None
        self._publishers: OrderedDict[str, Any] = OrderedDict()  # used by the worker only
        self._stopping = threading.Event()

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        """Declare the subscriber on the session and start the worker.

        Raises:
            IngestError: already started, or zenoh refuses the subscriber (e.g. the session
                is closed).
        """
        import zenoh

        if self._thread is not None:
            raise IngestError("ingest already started")
        try:
            self._subscriber = self._session.declare_subscriber(
                ALL_KEYFRAMES, zenoh.handlers.FifoChannel(self._capacity)
            )
        except zenoh.ZError as exc:
            raise IngestError(f"cannot subscribe to {ALL_KEYFRAMES}: {first_line(exc)}") from exc
        self._stopping.clear()
        # The worker reads the channel, not the subscriber: undeclaring the subscriber from
        # stop() closes the channel, and recv() then ends once the channel is empty.
        self._thread = threading.Thread(
            target=self._run, args=(self._subscriber.handler,), name="wardmap-ingest", daemon=True
        )
        self._thread.start()
        log.info("ingest subscribed to %s (FIFO capacity %d)", ALL_KEYFRAMES, self._capacity)

    def stop(self, timeout_s: float = 10.0) -> None:
        """Undeclare the subscriber (which closes the channel), join the worker, then undeclare
        its ack publishers (idempotent). The session stays open; its owner closes it.

        Samples still in the channel are stored but not acked; robots resend them and get
        ``duplicate`` for any that were stored.
        """
        self._stopping.set()
        subscriber, self._subscriber = self._subscriber, None
        if subscriber is not None:
            subscriber.undeclare()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout_s)
            if thread.is_alive():  # its publishers go when the owner closes the session
                log.warning("ingest worker did not stop within %.1f s", timeout_s)
                return
        while self._publishers:
            self._publishers.popitem()[1].undeclare()
        if thread is not None:
            log.info("ingest stopped")

    def __enter__(self) -> Ingest:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def counters(self) -> IngestCounters:
        """The counters now (consistent snapshot)."""
        with self._lock:
            c = dict(self._counts)
            depth = len(self._backlog)
        return IngestCounters(
            c["received"], c["stored"], c["duplicates"], c["rejected"], depth, c["ack_failures"]
        )

    # ------------------------------------------------------------------ worker

    def _count(self, name: str) -> None:
        with self._lock:
            self._counts[name] += 1

    def _run(self, sub: Any) -> None:
        import zenoh

        while True:
            try:
                first = sub.recv()  # blocks; raises ZError once the session closed and the channel is empty
            except zenoh.ZError:
                break
            # Take whatever else is already waiting (up to the capacity), so the backlog is visible.
            with self._lock:
                self._backlog.append(first)
            for _ in range(self._capacity - 1):
                nxt = sub.try_recv()
                if nxt is None:
                    break
                with self._lock:
                    self._backlog.append(nxt)
            while True:
                with self._lock:
                    if not self._backlog:
                        break
                    sample = self._backlog.popleft()
                self._handle(sample)
        with self._lock:
            self._backlog.clear()
        log.debug("ingest worker ends")

    def _handle(self, sample: Any) -> None:
        self._count("received")
        key = str(sample.key_expr)
        payload: bytes = b""
        try:
            payload = sample.payload.to_bytes()
            self._process(key, payload)
        except Exception:
            log.exception("internal error on a %d-byte sample on %s", len(payload), key[:200])
            self._count("rejected")
            self._count_rejection("internal")

    def _process(self, key: str, payload: bytes) -> None:
        try:
            key_robot: str | None = robot_id_from_key(key)
        except ConfigError:
            key_robot = None
        try:
            msg = decode_keyframe(payload)
        except WireError as exc:
            self._reject(wire_reason(exc.field), key_robot, None, str(exc))
            return
        if key_robot != msg.robot_id:
            self._reject("robot_id mismatch", key_robot, msg, f"key robot {key_robot!r} != robot_id")
            return
        try:
            result = self._store.insert(msg, payload, float(self._clock()))
        except WardmapError as exc:
            log.error("store rejected keyframe %s/%s/%d: %s", msg.robot_id, msg.session_id, msg.seq, exc)
            self._reject("store", key_robot, msg, "server could not store the keyframe")
            return
        self._count("stored" if result == "stored" else "duplicates")
        self._ack(msg.robot_id, AckMsg(msg.robot_id, msg.session_id, msg.seq, result))

    def _reject(self, reason: str, robot: str | None, msg: Any, detail: str) -> None:
        self._count("rejected")
        self._count_rejection(reason)
        log.debug("rejected sample (%s): %s", reason, detail)
        if robot is None:
            return
        session_id, seq = ("unknown", 0) if msg is None else (msg.session_id, msg.seq)
        status: AckStatus = "rejected"
        try:
            ack = AckMsg(robot, session_id, seq, status, detail[:_MAX_REASON])
        except WireError:  # the message's ids are valid by construction; be safe anyway
            return
        self._ack(robot, ack)

    def _count_rejection(self, reason: str) -> None:
        try:
            self._store.count_rejection(reason)
        except WardmapError as exc:
            log.error("cannot count rejection %r: %s", reason, exc)

    def _ack(self, robot_id: str, ack: AckMsg) -> None:
        import zenoh

        if self._stopping.is_set():
            return
        try:
            pub = self._publishers.get(robot_id)
            if pub is None:
                pub = self._session.declare_publisher(
                    ack_key(robot_id),
                    reliability=zenoh.Reliability.RELIABLE,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
                self._publishers[robot_id] = pub
                if len(self._publishers) > MAX_ACK_PUBLISHERS:
                    _, old = self._publishers.popitem(last=False)
                    old.undeclare()
            else:
                self._publishers.move_to_end(robot_id)
            pub.put(encode(ack))
        except (zenoh.ZError, WardmapError) as exc:
            self._count("ack_failures")
            log.warning("cannot ack %s/%s/%d: %s", ack.robot_id, ack.session_id, ack.seq, exc)
