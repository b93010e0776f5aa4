"""Zenoh peers that tests run inside their own process: a router on a thread, and an acker that
stands in for the server's ingest. Sessions are clients on loopback with shared memory and
multicast scouting off (``client_config``)."""

from __future__ import annotations

import json
import queue
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from procs import free_port

from wardmap.shared.wire import AckMsg, AckStatus, decode_keyframe, encode
from wardmap.shared.zenoh_config import ALL_KEYFRAMES, ack_key, client_config

ALL_ACKS = "wardmap/v1/robot/*/ack"
"""Subscription key for the acks to every robot."""


def open_client(endpoint: str) -> Any:
    """A zenoh client session connected to ``endpoint``."""
    import zenoh

    return zenoh.open(zenoh.Config.from_json5(json.dumps(client_config([endpoint]))))


def matched_publisher(session: Any, key: str, timeout_s: float) -> Any:
    """A publisher on ``key``, reliable with congestion control BLOCK (as robots publish),
    returned once a subscriber matches it, so nothing it puts goes to nobody."""
    import zenoh

    pub = session.declare_publisher(
        key, reliability=zenoh.Reliability.RELIABLE, congestion_control=zenoh.CongestionControl.BLOCK
    )
    matched = threading.Event()
    with pub.declare_matching_listener(lambda s: matched.set() if s.matching else None):
        if pub.matching_status.matching:
            matched.set()
        if not matched.wait(timeout_s):
            raise AssertionError(f"no subscriber matched {key} within {timeout_s} s")
    return pub


@contextmanager
def router_on_thread(timeout_s: float = 15.0) -> Iterator[str]:
    """A zenoh router (``run_router``) on a worker thread, on a free loopback port; yields its
    endpoint ``tcp/127.0.0.1:PORT`` once it is ready and stops it on exit."""
    from wardmap.server.router import run_router

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    stop, ready = threading.Event(), threading.Event()
    errors: list[BaseException] = []

    def target() -> None:
        try:
            run_router([endpoint], stop=stop, on_ready=lambda _e: ready.set())
        except BaseException as exc:  # surfaced below
            errors.append(exc)
            ready.set()

    worker = threading.Thread(target=target, name="test-router", daemon=True)
    worker.start()
    try:
        if not ready.wait(timeout_s) or errors:
            raise RuntimeError(f"router not ready within {timeout_s} s: {errors}")
        yield endpoint
    finally:
        stop.set()
        worker.join(10)


class Acker:
    """Stands in for the server: acks every keyframe it decodes with ``status`` (and ``reason``).

    The subscriber callback only enqueues (bounded queue, blocking: the test must see every
    keyframe); a worker thread decodes, records ``(session_id, seq)`` and the keyframe's poses
    (``poses``: ``(T_odom_base, T_odom_camera, T_map_odom)``) and publishes the ack.
    """

    def __init__(self, endpoint: str, status: AckStatus = "stored", reason: str = "") -> None:
        self.endpoint = endpoint
        self.status, self.reason = status, reason
        self.received: list[tuple[str, int]] = []  # owned by the worker; read under _lock
        self.poses: dict[tuple[str, int], tuple[Any, Any, Any]] = {}  # likewise
        self.images: dict[tuple[str, int], tuple[float, bytes]] = {}  # likewise: (stamp, rgb_jpeg)
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._queue: queue.Queue[bytes | None] = queue.Queue(maxsize=256)
        self._session: Any = None
        self._worker = threading.Thread(target=self._work, name="acker", daemon=True)

    def __enter__(self) -> Acker:
        self._session = open_client(self.endpoint)
        self._sub = self._session.declare_subscriber(
            ALL_KEYFRAMES, lambda s: self._queue.put(s.payload.to_bytes())
        )
        self._worker.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._queue.put(None)
        self._worker.join(timeout=10)
        self._sub.undeclare()
        self._session.close()

    def _work(self) -> None:
        while (payload := self._queue.get()) is not None:
            msg = decode_keyframe(payload)
            ack = AckMsg(msg.robot_id, msg.session_id, msg.seq, self.status, self.reason)
            self._session.put(ack_key(msg.robot_id), encode(ack))
            with self._changed:
                self.received.append((msg.session_id, msg.seq))
                self.poses[(msg.session_id, msg.seq)] = (msg.T_odom_base, msg.T_odom_camera, msg.T_map_odom)
                self.images[(msg.session_id, msg.seq)] = (msg.stamp, msg.rgb_jpeg)
                self._changed.notify_all()

    def keys(self) -> set[tuple[str, int]]:
        with self._lock:
            return set(self.received)

    def wait_for(self, keys: set[tuple[str, int]], timeout_s: float) -> bool:
        """True once every key in ``keys`` was received."""
        with self._changed:
            return self._changed.wait_for(lambda: keys <= set(self.received), timeout=timeout_s)
