"""Keyframe ingest: zenoh subscriber -> decode + validate -> store -> ack.

:class:`Ingest` declares, on the server's one zenoh session (opened and closed by the
composition root, ``server/app.py``), one subscriber on
:data:`~wardmap.shared.zenoh_config.ALL_KEYFRAMES` and one ack publisher per robot, and runs
one worker thread. The subscriber's callback only puts each sample into a :class:`SampleQueue`
that the worker reads. :meth:`Ingest.stop` undeclares all of them; the session outlives it.

Queue policy: **FIFO, bounded in samples and in payload bytes, block when full
(backpressure, never drop)**. When the queue holds ``capacity`` samples or ``max_bytes`` of
payload, the callback waits, so zenoh stops taking samples off the transport; the robots
publish reliable with congestion control ``BLOCK``, so their puts wait instead of being
dropped. A message larger than the session's ``max_message_size`` (``shared/zenoh_config.py``,
a little over the wire's 4 MiB) is dropped by zenoh before it is reassembled, so a queue of
``max_bytes`` holds at most ``max_bytes`` plus one such message.

For each sample the worker decodes the keyframe, checks that the robot id in the key equals
the message's ``robot_id``, stores it and only *after* the insert committed hands the decoded
message of a newly stored keyframe to the stages (:class:`~wardmap.server.decoded.DecodedCache`:
a keyframe is decoded once per process) and publishes an
:class:`~wardmap.shared.wire.AckMsg` (``stored`` or ``duplicate``) on
:func:`~wardmap.shared.zenoh_config.ack_key`. Bad input never stops the worker: a message that
can never be stored (a :class:`~wardmap.shared.errors.WireError`, a robot id mismatch) is
counted as a rejection and acked ``rejected`` when the robot is known; an unexpected exception
is logged with the payload size and counted as ``internal`` (not acked: the robot resends).

An ack means stored, and only then. When the store fails on a valid keyframe (disk or page cap
full, locked past the busy timeout, I/O error, damaged file: any
:class:`~wardmap.server.store.StoreError`) the keyframe is acked ``retry`` and counted in
``retry_later``; the robot keeps it in its outbox and resends it. Rejection counts are kept in
memory first and written to the store whenever it can write (at once, after the next stored
keyframe, at most every :data:`PERSIST_RETRY_S` while it cannot, and when the worker ends), each
count exactly once: :meth:`Ingest.counters` shows those not written yet and
:meth:`Ingest.rejections` the sum. :meth:`Ingest.ready` says whether keyframes can be stored now.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Final

from wardmap.server.decoded import DecodedCache, keyframe_key
from wardmap.server.store import KeyframeStore, StoreDamagedError, StoreError
from wardmap.server.telemetry import ServerTelemetry
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

__all__ = ["DEFAULT_CAPACITY", "DEFAULT_MAX_BYTES", "Ingest", "IngestCounters", "IngestError", "SampleQueue"]

DEFAULT_CAPACITY: Final = 256
"""Samples the ingest queue holds before zenoh applies backpressure."""
DEFAULT_MAX_BYTES: Final = 64 * 2**20
"""Payload bytes the ingest queue holds before zenoh applies backpressure (64 MiB: 16
keyframes of the wire's largest, or a few hundred of a robot's usual 100-200 KB)."""
MAX_ACK_PUBLISHERS: Final = 1024
"""Ack publishers kept declared (one per robot); the least recently used is undeclared beyond this."""
_MAX_REASON: Final = 200
PERSIST_RETRY_S: Final = 5.0
"""While the store cannot write, rejection counts are retried at most this often (each try may
wait the store's busy timeout) and after every keyframe stored."""


class IngestError(WardmapError):
    """The ingest cannot start (already started, zenoh refuses the subscriber)."""


class SampleQueue:
    """A FIFO bounded in items and in bytes: :meth:`put` blocks while full, :meth:`get` while
    empty; thread safe. An item larger than ``max_bytes`` is taken when the queue is empty
    (it can never fit otherwise). After :meth:`close`, ``put`` refuses and ``get`` returns
    what is left, then None."""

    def __init__(self, capacity: int, max_bytes: int) -> None:
        self._capacity = capacity
        self._max_bytes = max_bytes
        self._items: deque[tuple[Any, int]] = deque()
        self._bytes = 0
        self._closed = False
        self._cond = threading.Condition()

    def put(self, item: Any, size: int) -> bool:
        """Append ``item`` of ``size`` bytes once it fits; False (not queued) when closed."""
        with self._cond:
            while not self._closed and self._items and (
                len(self._items) >= self._capacity or self._bytes + size > self._max_bytes
            ):
                self._cond.wait()
            if self._closed:
                return False
            self._items.append((item, size))
            self._bytes += size
            self._cond.notify_all()
            return True

    def get(self) -> Any:
        """The oldest item, waiting for one; None once closed and empty."""
        with self._cond:
            while not self._items and not self._closed:
                self._cond.wait()
            if not self._items:
                return None
            item, size = self._items.popleft()
            self._bytes -= size
            self._cond.notify_all()
            return item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def depth(self) -> tuple[int, int]:
        """``(items, bytes)`` queued now."""
        with self._cond:
            return len(self._items), self._bytes


@dataclass(frozen=True, slots=True)
class IngestCounters:
    """A snapshot of the ingest's counters since :meth:`Ingest.start`.

    Attributes:
        received: samples taken from the channel.
        stored: keyframes newly stored (and acked ``stored``).
        duplicates: keyframes already stored (acked ``duplicate``).
        rejected: samples rejected (bad payload, key/robot mismatch, internal); never a
            storage failure.
        queue_depth: samples queued and not yet taken by the worker.
        ack_failures: acks that could not be published.
        retry_later: valid keyframes the store could not take (acked ``retry``; the robot resends).
        unpersisted_rejections: rejection counts by reason not yet written to the store (it
            could not write); added to the store's once it can.
        queued_bytes: payload bytes of the queued samples (at most ``max_bytes`` plus one sample).
    """

    received: int
    stored: int
    duplicates: int
    rejected: int
    queue_depth: int
    ack_failures: int
    retry_later: int = 0
    unpersisted_rejections: Mapping[str, int] = field(default_factory=dict)
    queued_bytes: int = 0


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
        max_bytes: int = DEFAULT_MAX_BYTES,
        clock: Any = time.time,
        telemetry: ServerTelemetry | None = None,
        decoded: DecodedCache | None = None,
    ) -> None:
        """
        Args:
            session: the process's open ``zenoh.Session``; it must outlive this object's
                ``stop()`` (its owner closes it after).
            store: where keyframes go; it must outlive this object's ``stop()``.
            capacity: most samples queued (>= 1).
            max_bytes: most payload bytes queued (>= 1; one larger sample passes alone).
            clock: wall-clock seconds for ``received_s`` (``time.time``).
            telemetry: where ingest and ack latencies and per-robot series go (a private one
                when None).
            decoded: where each newly stored keyframe's decoded message goes, so the back-end
                and the mapping stage do not decode it again (``server/decoded.py``); None:
                nowhere (no stage runs in this process).
        """
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise ConfigError(f"ingest capacity must be an int >= 1, got {capacity!r}")
        if isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or max_bytes < 1:
            raise ConfigError(f"ingest max_bytes must be an int >= 1, got {max_bytes!r}")
        self._session = session
        self._store = store
        self._capacity = capacity
        self._max_bytes = max_bytes
        self._clock = clock
        self._telemetry = telemetry if telemetry is not None else ServerTelemetry()
        self._decoded = decoded
        self._lock = threading.Lock()
        self._counts = {"received": 0, "stored": 0, "duplicates": 0, "rejected": 0, "ack_failures": 0,
                        "retry_later": 0}
        self._unpersisted: Counter[str] = Counter()  # rejections not in the store yet; under _lock
        self._persist_lock = threading.Lock()  # one store write + its _unpersisted update at a time
        self._store_fault: str | None = None  # worker only: why the last insert failed, None once it works
        self._next_persist = 0.0  # worker only: after a failed count write, none before this (monotonic)
        self._queue: SampleQueue | None = None
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
        queue = SampleQueue(self._capacity, self._max_bytes)

        def on_sample(sample: Any) -> None:  # zenoh's thread: enqueue only (blocks while full)
            queue.put(sample, len(sample.payload))

        try:
            self._subscriber = self._session.declare_subscriber(ALL_KEYFRAMES, on_sample)
        except zenoh.ZError as exc:
            raise IngestError(f"cannot subscribe to {ALL_KEYFRAMES}: {first_line(exc)}") from exc
        self._stopping.clear()
        self._queue = queue
        self._thread = threading.Thread(target=self._run, args=(queue,), name="wardmap-ingest", daemon=True)
        self._thread.start()
        log.info("ingest subscribed to %s (FIFO of %d samples, %d bytes)", ALL_KEYFRAMES, self._capacity,
                 self._max_bytes)

    def stop(self, timeout_s: float = 10.0) -> None:
        """Undeclare the subscriber (which closes the channel), join the worker, then undeclare
        its ack publishers (idempotent). The session stays open; its owner closes it.

        Samples still queued are stored but not acked; robots resend them and get
        ``duplicate`` for any that were stored.
        """
        self._stopping.set()
        if self._queue is not None:
            # First: a callback waiting on a full queue returns (its sample is not acked, so its
            # robot resends it), and undeclaring cannot wait on it. The worker empties the queue.
            self._queue.close()
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
            unpersisted = dict(self._unpersisted)
        depth, queued_bytes = (0, 0) if self._queue is None else self._queue.depth()
        return IngestCounters(
            c["received"], c["stored"], c["duplicates"], c["rejected"], depth, c["ack_failures"],
            c["retry_later"], unpersisted, queued_bytes,
        )

    def rejections(self) -> dict[str, int]:
        """Every rejection reason with its count: the store's plus those not written yet, each
        counted once (thread safe; for ``/metrics``).

        Raises:
            StoreError: the store cannot be read (e.g. :class:`StoreDamagedError`).
        """
        with self._persist_lock:  # no count moves from memory to the store meanwhile
            counts = Counter(self._store.rejections())
            with self._lock:
                counts.update(self._unpersisted)
        return dict(sorted(counts.items()))

    def ready(self) -> tuple[bool, str]:
        """Whether this ingest can store keyframes now: ``(True, "ok")`` or ``(False, why)``,
        for ``/readyz``: the worker runs and :meth:`KeyframeStore.writable` passes. Thread
        safe; never raises; may take up to the store's probe timeout (about 1 s) while
        another process holds the database's write lock."""
        thread = self._thread
        if thread is None or not thread.is_alive() or self._stopping.is_set():
            return False, "ingest is not running"
        ok, why = self._store.writable()
        return (True, "ok") if ok else (False, f"keyframe store cannot write: {why}")

    # ------------------------------------------------------------------ worker

    def _count(self, name: str) -> None:
        with self._lock:
            self._counts[name] += 1

    def _run(self, queue: SampleQueue) -> None:
        while (sample := queue.get()) is not None:
            self._handle(sample)
        self._persist_rejections()  # last chance for counts kept while the store could not write
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
        started = time.perf_counter()
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
        except StoreError as exc:
            # The server's own failure, never the message's: the robot keeps it and resends.
            self._retry_later(msg, exc)
            return
        if result == "stored" and self._decoded is not None:
            self._decoded.put(keyframe_key(msg), msg, len(payload))
        self._telemetry.ingest_seconds.observe(time.perf_counter() - started)
        self._telemetry.keyframe(msg.robot_id, result, time.time())
        if self._store_fault is not None:
            log.warning("keyframe store writes again (was: %s)", self._store_fault)
            self._store_fault = None
        self._count("stored" if result == "stored" else "duplicates")
        self._ack(msg.robot_id, AckMsg(msg.robot_id, msg.session_id, msg.seq, result))
        if self._unpersisted:  # read without the lock: only this thread adds to it
            self._persist_rejections()

    def _retry_later(self, msg: KeyframeMsg, exc: StoreError) -> None:
        """Ack ``retry``: the keyframe is valid but was not stored; logged once per fault."""
        self._count("retry_later")
        self._telemetry.keyframe(msg.robot_id, "retry", time.time())
        damaged = isinstance(exc, StoreDamagedError)
        kind = "damaged" if damaged else "cannot store"
        if self._store_fault is None:
            # The store logged how to repair a damaged file once already; do not repeat it.
            why = "the store logged how to repair it" if damaged else str(exc)
            log.error("keyframe store %s (%s): keyframes are acked 'retry' and stay on the robots "
                      "until it can store them", kind, why)
        else:
            log.debug("keyframe %s/%s/%d not stored: %s", msg.robot_id, msg.session_id, msg.seq, exc)
        self._store_fault = kind if damaged else str(exc)
        detail = f"server storage: {kind}; resend later"
        self._ack(msg.robot_id, AckMsg(msg.robot_id, msg.session_id, msg.seq, "retry", detail))

    def _reject(self, reason: str, robot: str | None, msg: Any, detail: str) -> None:
        self._count("rejected")
        self._count_rejection(reason)
        log.debug("rejected sample (%s): %s", reason, detail)
        if robot is None:
            return
        self._telemetry.keyframe(robot, "rejected", time.time())
        session_id, seq = ("unknown", 0) if msg is None else (msg.session_id, msg.seq)
        status: AckStatus = "rejected"
        try:
            ack = AckMsg(robot, session_id, seq, status, detail[:_MAX_REASON])
        except WireError:  # the message's ids are valid by construction; be safe anyway
            return
        self._ack(robot, ack)

    def _count_rejection(self, reason: str) -> None:
        """Count ``reason`` in memory, then try to write every count kept so far to the store."""
        with self._lock:
            self._unpersisted[reason] += 1
        if time.monotonic() >= self._next_persist:  # not while a recent try failed: each waits
            self._persist_rejections()

    def _persist_rejections(self) -> None:
        """Move the in-memory rejection counts into the store, one reason per transaction; a
        count leaves memory only once its transaction committed, so none is lost or doubled."""
        with self._persist_lock:
            with self._lock:
                todo = list(self._unpersisted.items())
            for reason, n in todo:
                try:
                    self._store.count_rejection(reason, n)
                except WardmapError as exc:
                    self._next_persist = time.monotonic() + PERSIST_RETRY_S
                    log.warning("cannot write rejection counts yet (kept in memory): %s", exc)
                    return
                with self._lock:
                    self._unpersisted[reason] -= n
                    if self._unpersisted[reason] <= 0:
                        del self._unpersisted[reason]

    def _ack(self, robot_id: str, ack: AckMsg) -> None:
        import zenoh

        if self._stopping.is_set():
            return
        started = time.perf_counter()
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
            self._telemetry.ack_seconds.observe(time.perf_counter() - started)
        except (zenoh.ZError, WardmapError) as exc:
            self._count("ack_failures")
            log.warning("cannot ack %s/%s/%d: %s", ack.robot_id, ack.session_id, ack.seq, exc)
