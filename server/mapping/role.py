"""Which of several servers on one store runs the mapping stage: the holder of the writer lease.

The mapping stage and its back-end (``stage.py``, ``server/backend/stage.py``) are the only
writers of the cursors, measurements, pose graph, checkpoint and object map; two of them on one
database would corrupt each other's work. :class:`MappingRole` owns the store's
:class:`~wardmap.server.store.WriterLease` and, only while it holds it, one
:class:`~wardmap.server.mapping.stage.MapPipeline`, built anew by a factory each time the lease
is taken: the new writer restores the pose graph and the association checkpoint its
predecessor committed and goes on after their cursors (they move in the same transactions as
the rows they cover, so nothing is lost or done twice).

One thread checks the lease every ``poll_s`` seconds: a standby tries to take it; the holder
asks the database whether it still holds it and stops its stage as soon as it does not (its
lease connection died). A holder whose stage stopped running (its thread died) gives the
lease back, so that a standby, or a new stage here, maps instead.

Takeover time: the holder's process dies -> the database ends its lease connection at once (a
killed process's socket closes; a silent host or network: TCP keepalive, about 5 s,
``store/postgres.py``) -> a standby takes the lease within ``poll_s`` and starts its stage
(restore + replay after the checkpoint). SQLite serves one server, whose
lease is always granted: the stage starts with the server, as it always has.

A standby stores keyframes and answers REST and Zenoh queries from the shared store like the
writer; only the writer's object map emits change events (``wardmap/v1/map/updates``, the web
page's stream).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

from wardmap.server.mapping.stage import MapPipeline
from wardmap.server.store import WriterLease

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_POLL_S", "LeaseState", "MappingRole"]

DEFAULT_POLL_S: Final = 1.0
"""How often (seconds) the lease is checked or tried."""


@dataclass(frozen=True, slots=True)
class LeaseState:
    """The writer lease as this server sees it (``/readyz``, ``/metrics``).

    Attributes:
        held: this server holds the lease (it runs the mapping stage).
        holder: who holds it (this server's name when held), None when nobody does or the
            database could not tell at the last check.
        name: this server's holder name.
    """

    held: bool
    holder: str | None
    name: str


class MappingRole:
    """Runs the mapping stage while this server holds the writer lease; see the module docstring.

    Args:
        lease: this server's handle on the store's writer lease (not acquired).
        make_pipeline: builds a new, unstarted mapping stage (its back-end included).
        poll_s: seconds between two checks of the lease.
        on_running: told True before a mapping stage starts here and False after it stopped
            (or failed to start): what only a running stage consumes, such as ingest's decoded
            keyframes, is kept only then.
    """

    def __init__(self, lease: WriterLease, make_pipeline: Callable[[], MapPipeline], *,
                 poll_s: float = DEFAULT_POLL_S, on_running: Callable[[bool], None] | None = None) -> None:
        self._lease = lease
        self._make = make_pipeline
        self._on_running = on_running if on_running is not None else (lambda running: None)
        self._poll_s = poll_s
        self._lock = threading.Lock()  # guards _pipeline and _holder for readers on other threads
        self._pipeline: MapPipeline | None = None  # the role's thread (or start/stop) replaces it
        self._holder: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Try the lease once and, when it is granted, start the mapping stage here (its errors
        propagate, the lease given back); then start the thread that keeps checking."""
        if self._lease.acquire():
            try:
                self._start_pipeline()
            except BaseException:
                self._lease.release()
                raise
        else:
            log.info("writer lease held by %s: this server (%s) is a standby",
                     self._lease.current_holder() or "another server", self._lease.holder)
        self._refresh_holder()
        self._stop.clear()
        self._thread = threading.Thread(target=self._main, name="writer-lease", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread, the mapping stage (when running) and give the lease back (idempotent)."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join()
        self._stop_pipeline()
        self._lease.release()

    @property
    def pipeline(self) -> MapPipeline | None:
        """The running mapping stage, None while this server is a standby."""
        with self._lock:
            return self._pipeline

    def state(self) -> LeaseState:
        """The lease as of the last check (cheap: no database call)."""
        with self._lock:
            return LeaseState(self._pipeline is not None, self._holder, self._lease.holder)

    def running(self) -> bool:
        """Whether the lease thread runs (started, not stopped)."""
        thread = self._thread
        return thread is not None and thread.is_alive() and not self._stop.is_set()

    # ------------------------------------------------------------------ thread

    def _main(self) -> None:
        while not self._stop.wait(self._poll_s):
            try:
                self._check()
            except Exception:
                log.exception("writer lease: unexpected error; checking again in %.1f s", self._poll_s)

    def _check(self) -> None:
        pipeline = self.pipeline
        if pipeline is not None:
            if not pipeline.running():  # its thread died: let another server (or a new stage) map
                log.error("mapping stage stopped running: giving the writer lease back")
                self._stop_pipeline()
                self._lease.release()
            elif self._lease.held():
                return
            else:
                log.warning("writer lease lost (its database connection ended): stopping the mapping stage; "
                            "another server takes over")
                self._stop_pipeline()
                self._lease.release()
        if self._lease.acquire():
            log.info("writer lease taken by %s: starting the mapping stage", self._lease.holder)
            try:
                self._start_pipeline()
            except Exception:
                log.exception("mapping stage did not start; giving the writer lease back")
                self._lease.release()
        self._refresh_holder()

    def _start_pipeline(self) -> None:
        pipeline = self._make()
        self._on_running(True)
        try:
            pipeline.start()
        except BaseException:
            self._on_running(False)
            raise
        with self._lock:
            self._pipeline = pipeline
            self._holder = self._lease.holder

    def _stop_pipeline(self) -> None:
        with self._lock:
            pipeline, self._pipeline = self._pipeline, None
        if pipeline is not None:
            pipeline.stop()
            self._on_running(False)

    def _refresh_holder(self) -> None:
        holder = self._lease.holder if self.pipeline is not None else self._lease.current_holder()
        with self._lock:
            self._holder = holder
