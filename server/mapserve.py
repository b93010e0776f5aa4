"""The object map over Zenoh: a queryable for robots and a stream of map updates.

:class:`MapServe` declares, on the server's one zenoh session (opened and closed by the
composition root, ``server/app.py``),

- a queryable on :data:`OBJECTS_KEY` (``wardmap/v1/map/objects``) that answers the filters
  of ``GET /v1/objects`` given as selector parameters, e.g.
  ``wardmap/v1/map/objects?category=door;near=1,2,0;radius=3`` (keys ``category``,
  ``near``, ``radius``, ``min_confidence``, ``robot``, ``limit``, ``offset``,
  ``include_unconfirmed``; zenoh's own ``_``-prefixed parameters are ignored). One reply
  :class:`~wardmap.shared.mapwire.ObjectsReply`; bad parameters get a reply error
  :class:`~wardmap.shared.mapwire.MapError` naming the parameter.
- a publisher on :data:`UPDATES_KEY` (``wardmap/v1/map/updates``), reliable with congestion
  control ``BLOCK``, that sends one :class:`~wardmap.shared.mapwire.MapUpdate` for every
  :class:`~wardmap.server.objectmap.ObjectChange`, in commit order.

:meth:`MapServe.stop` undeclares both; the session outlives it.

Queue policy: queries reach the worker thread through a bounded zenoh FIFO channel
(``FifoChannel(capacity)``): **FIFO, block when full** (zenoh applies backpressure, nothing
is dropped). Updates are published from the object map's listener on the writer's thread
after each commit, so a slow subscriber slows the map writer instead of losing updates; a
failed put is logged and counted (``update_failures``).

The messages are defined in ``shared/mapwire.py`` (robots decode them without importing
the server); ``server/mapmessages.py`` builds them from the map's records, as the REST API
does, so an object has one shape in both (docs/map_api.md).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Any, Final

from wardmap.server.mapmessages import map_update, objects_reply
from wardmap.server.objectmap import ObjectChange, ObjectMap, ObjectMapError, ObjectQuery
from wardmap.server.zenoh_session import first_line
from wardmap.shared.errors import ConfigError, WardmapError
from wardmap.shared.mapwire import (
    ENCODING,
    MAX_DETAIL_LEN,
    OBJECTS_KEY,
    UPDATES_KEY,
    MapError,
    encode_map_message,
)

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_CAPACITY",
    "OBJECTS_KEY",
    "UPDATES_KEY",
    "MapServe",
    "MapServeCounters",
    "MapServeError",
]

DEFAULT_CAPACITY: Final = 64
"""Queries the zenoh FIFO channel holds before zenoh applies backpressure."""


class MapServeError(WardmapError):
    """The map service cannot start (already started, zenoh refuses a declaration)."""


@dataclass(frozen=True, slots=True)
class MapServeCounters:
    """Counts since :meth:`MapServe.start`.

    Attributes:
        queries: queries answered with objects.
        query_errors: queries answered with a reply error (bad parameters, store failure).
        updates: updates published.
        update_failures: updates that could not be published (logged).
    """

    queries: int
    query_errors: int
    updates: int
    update_failures: int


class MapServe:
    """Serve the object map over zenoh; see the module docstring.

    Use ``start()`` / ``stop()`` or a ``with`` block. :meth:`counters` may be called from
    any thread.
    """

    def __init__(self, session: Any, objects: ObjectMap, *, capacity: int = DEFAULT_CAPACITY) -> None:
        """
        Args:
            session: the process's open ``zenoh.Session``; it must outlive this object's
                ``stop()`` (its owner closes it after).
            objects: the map; it must outlive this object's ``stop()``.
            capacity: size of the queryable's FIFO channel (>= 1).
        """
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise ConfigError(f"map service capacity must be an int >= 1, got {capacity!r}")
        self._session = session
        self._objects = objects
        self._capacity = capacity
        self._lock = threading.Lock()  # guards the counts
        self._counts = {"queries": 0, "query_errors": 0, "updates": 0, "update_failures": 0}
        # Held while a put is in flight, so stop() never undeclares the publisher under it.
        self._publish_lock = threading.Lock()
        self._publisher: Any = None
        self._queryable: Any = None
        self._remove_listener: Any = None
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        """Declare the queryable and the publisher on the session, start the worker.

        Raises:
            MapServeError: already started, or zenoh refuses a declaration (e.g. the session
                is closed).
        """
        import zenoh

        if self._thread is not None:
            raise MapServeError("map service already started")
        try:
            queryable = self._session.declare_queryable(
                OBJECTS_KEY, zenoh.handlers.FifoChannel(self._capacity), complete=True
            )
        except zenoh.ZError as exc:
            raise MapServeError(f"cannot declare the queryable {OBJECTS_KEY}: {first_line(exc)}") from exc
        try:
            publisher = self._session.declare_publisher(
                UPDATES_KEY,
                encoding=ENCODING,
                reliability=zenoh.Reliability.RELIABLE,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
        except zenoh.ZError as exc:
            queryable.undeclare()
            raise MapServeError(f"cannot declare the publisher {UPDATES_KEY}: {first_line(exc)}") from exc
        self._queryable = queryable
        with self._publish_lock:
            self._publisher = publisher
        self._remove_listener = self._objects.add_listener(self._publish)
        # The worker reads the channel, not the queryable: undeclaring the queryable from
        # stop() closes the channel, and recv() then ends once the channel is empty.
        self._thread = threading.Thread(
            target=self._run, args=(queryable.handler,), name="wardmap-mapserve", daemon=True
        )
        self._thread.start()
        log.info("map service: queryable %s, updates on %s", OBJECTS_KEY, UPDATES_KEY)

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop publishing, undeclare the publisher and the queryable (which closes the
        channel), join the worker (idempotent). The session stays open; its owner closes it."""
        remove, self._remove_listener = self._remove_listener, None
        if remove is not None:
            remove()
        with self._publish_lock:  # waits for a put in flight
            publisher, self._publisher = self._publisher, None
            if publisher is not None:
                publisher.undeclare()
        queryable, self._queryable = self._queryable, None
        if queryable is not None:
            queryable.undeclare()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout_s)
            if thread.is_alive():
                log.warning("map service worker did not stop within %.1f s", timeout_s)

    def __enter__(self) -> MapServe:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def counters(self) -> MapServeCounters:
        """The counters now (consistent snapshot)."""
        with self._lock:
            c = dict(self._counts)
        return MapServeCounters(c["queries"], c["query_errors"], c["updates"], c["update_failures"])

    # ------------------------------------------------------------------ work

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
                    log.exception("map query %s failed", str(query.selector)[:200])
                    self._reply_error(query, "internal error of the map server")
        log.debug("map service worker ends")

    def _answer(self, query: Any) -> None:
        params = [(str(k), str(v)) for k, v in query.parameters if not str(k).startswith("_")]
        try:
            page = self._objects.find(ObjectQuery.from_params(params))
        except ObjectMapError as exc:
            self._reply_error(query, str(exc))
            return
        except WardmapError as exc:
            log.error("map query %s: %s", str(query.selector)[:200], exc)
            self._reply_error(query, "the map server could not read the object map")
            return
        query.reply(OBJECTS_KEY, encode_map_message(objects_reply(page)), encoding=ENCODING)
        self._count("queries")

    def _reply_error(self, query: Any, detail: str) -> None:
        import zenoh

        self._count("query_errors")
        payload = encode_map_message(MapError(detail[:MAX_DETAIL_LEN] or "error"))
        try:
            query.reply_err(payload, encoding=ENCODING)
        except zenoh.ZError as exc:
            log.warning("cannot answer map query %s: %s", str(query.selector)[:200], exc)

    def _publish(self, change: ObjectChange) -> None:
        """Object map listener: publish one update (on the writer's thread, after the commit)."""
        import zenoh

        object_id = change.record.object_id
        with self._publish_lock:
            publisher = self._publisher
            if publisher is None:
                self._count("update_failures")
                log.warning("map update of object %d not published: the map service is stopped", object_id)
                return
            try:
                publisher.put(encode_map_message(map_update(change)))
            except (zenoh.ZError, WardmapError) as exc:
                self._count("update_failures")
                log.warning("cannot publish map update of object %d: %s", object_id, exc)
                return
        self._count("updates")
