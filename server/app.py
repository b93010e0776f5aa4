"""The map server process: its composition root and ``run_server``.

:class:`MapServer` is the composition root. Built from the settings, it opens nothing; its
``start()`` opens the keyframe store, builds the object map on it, opens the process's one
Zenoh session (:func:`~wardmap.server.zenoh_session.open_session`) and starts on it the
keyframe :class:`~wardmap.server.ingest.Ingest` and the :class:`~wardmap.server.mapserve.MapServe`,
then the mapping stage; ``stop()`` stops them in reverse order. Its ``app`` is the REST API
(:func:`wardmap.server.api.create_app`), whose HTTP lifespan only calls ``start()`` and
``stop()``.

Who owns what: the root owns the store, the session and every part; ingest and map service
own the declarations they make on the session and undeclare them in ``stop()``; the root
closes the session after both stopped (a session left open keeps the process from exiting),
then the store.

:func:`run_server` checks what a user can get wrong up front (the store URL, the HTTP port)
so those fail with one clear :class:`ServerError`/:class:`StoreError`, then runs uvicorn on a
helper thread; the main thread handles the signals and waits on one event that either a
signal, the caller's ``stop`` or the end of the HTTP thread sets. What may come up later (a
database server, the router) is waited for instead: ``start()`` retries it with a warning per
attempt until it answers or that event is set (a stop while waiting exits cleanly).
"""

from __future__ import annotations

import dataclasses
import functools
import ipaddress
import logging
import os
import socket
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from typing import TYPE_CHECKING, Any, TypeVar

from wardmap.server.api import Services, create_app
from wardmap.server.corrections import CorrectionPublisher
from wardmap.server.decoded import DecodedCache
from wardmap.server.ingest import Ingest
from wardmap.server.mapping.role import MappingRole
from wardmap.server.mapserve import MapServe
from wardmap.server.objectmap import ObjectMap
from wardmap.server.retention import ImageRetention, RetentionConfig
from wardmap.server.store import StoreError, StoreUnavailableError, open_store
from wardmap.server.store.sqlbase import MAX_HOLDER_LEN, check_lease_holder
from wardmap.server.telemetry import ServerTelemetry
from wardmap.server.zenoh_session import ZenohSessionError, check_session_config, has_router, open_session
from wardmap.shared.errors import ConfigError, WardmapError
from wardmap.shared.signals import on_stop_signals
from wardmap.shared.zenoh_config import ZenohOptions, client_config

if TYPE_CHECKING:
    from fastapi import FastAPI

    from wardmap.server.mapping import MapPipeline, PipelineFactory
    from wardmap.server.mapping.workers import PerceptionWorkers
    from wardmap.server.store import MapStore

log = logging.getLogger(__name__)

__all__ = ["MapServer", "ServerError", "default_name", "is_loopback", "run_server"]

SHUTDOWN_TIMEOUT_S = 15.0
RETRY_FIRST_S = 1.0
"""First wait (seconds) before opening the store or the Zenoh session again at start-up."""
RETRY_MAX_S = 30.0
"""Longest wait between two attempts (the wait doubles from :data:`RETRY_FIRST_S`)."""

T = TypeVar("T")


class ServerError(WardmapError):
    """The map server cannot start (port in use, bad address, start-up failure)."""


class MapServer:
    """The composition root of one map server process; see the module docstring.

    Use ``start()`` / ``stop()``, a ``with`` block, or serve :attr:`app` (its lifespan starts
    and stops the server).
    """

    def __init__(
        self,
        db_url: str,
        *,
        connect: Sequence[str] | None = None,
        pipeline_factory: PipelineFactory | None = None,
        require_tokens: bool = True,
        telemetry: ServerTelemetry | None = None,
        retry_until: threading.Event | None = None,
        zenoh_options: ZenohOptions | None = None,
        db_password: str | None = None,
        retention: RetentionConfig | None = None,
        name: str | None = None,
        workers_factory: Callable[[str, str | None, str], PerceptionWorkers] | None = None,
    ) -> None:
        """
        Args:
            db_url: keyframe store URL, ``sqlite:///PATH`` or ``postgresql://USER@HOST:PORT/DB``
                (opened by ``start()``; :func:`~wardmap.server.store.open_store`).
            connect: zenoh router endpoints ``tcp/HOST:PORT`` or ``tls/HOST:PORT`` (checked
                now). The server opens one session to them for the ingest and the map
                service. None: no Zenoh (REST API only; tests, benchmarks).
            pipeline_factory: builds the mapping stage (``server/mapping/stage.py``) from the
                store, the object map and the keyframes ingest decoded; the writer-lease role
                runs it (``server/mapping/role.py``). None: keyframes are stored but not mapped.
            require_tokens: the REST API's data routes need a bearer token (``server/tokens.py``);
                False only for insecure-loopback mode (:func:`run_server` checks the address).
            telemetry: the histograms and per-robot series of this process (the pipeline
                factory's parts record into the same one); a new one when None.
            retry_until: when given, ``start()`` waits for a store that is unavailable or a
                router that does not answer, trying again with a capped backoff
                (:data:`RETRY_FIRST_S` doubling to :data:`RETRY_MAX_S`, a warning each attempt)
                until it succeeds or this event is set; None: fail at once.
            zenoh_options: TLS files and zenoh config file of the session (docs/security.md).
            db_password: the PostgreSQL password (``--db-password-file``); None: the store's
                own sources (``WARDMAP_DB_PASSWORD``, ``~/.pgpass``).
            retention: ``[store]`` image retention; the job runs when it sets one
                (``server/retention.py``). None: images are kept.
            name: this server's name in the store's writer lease (several servers on one
                database: the holder runs the mapping stage, ``server/mapping/role.py``);
                None: :func:`default_name`.
            workers_factory: builds this server's perception workers from the store URL, the
                password and the server's name (``server/mapping/workers.py``; they run on a
                standby too); None: none here.

        Raises:
            ConfigError: a bad endpoint in ``connect``.
        """
        if connect is not None:
            client_config(connect, options=zenoh_options)  # validates the endpoints now
        self._zenoh_options = zenoh_options
        self._retention = retention
        self.name = name if name is not None else default_name()
        """This server's name in the writer lease (``/readyz``, ``/metrics``)."""
        try:
            check_lease_holder(self.name)
        except StoreError as exc:
            raise ConfigError(f"bad server name: {exc}") from exc
        self._db_url = db_url
        self._db_password = db_password
        self._connect = None if connect is None else list(connect)
        self._pipeline_factory = pipeline_factory
        self._workers_factory = workers_factory
        self._telemetry = telemetry if telemetry is not None else ServerTelemetry()
        self._retry_until = retry_until
        self._cancelled = False  # start() gave up waiting because retry_until was set
        self._running: ExitStack | None = None
        self._services: Services | None = None
        self.app: FastAPI = create_app(self, require_tokens=require_tokens)
        """The REST API over this server; its lifespan calls :meth:`start` and :meth:`stop`."""

    def start(self) -> Services:
        """Open the store and the session, start ingest, map service and mapping stage.

        On failure, whatever started is stopped again (in reverse order) before the error
        propagates.

        Returns:
            The running parts the REST API reads.

        Raises:
            ServerError: already started, or ``retry_until`` was set while waiting.
            StoreError: the store cannot be opened.
            ZenohSessionError: no router answers at ``connect``.
            WardmapError: a part cannot start (its own error).
        """
        if self._running is not None:
            raise ServerError("map server already started")
        with ExitStack() as stack:  # closes in reverse on an error, until pop_all()
            store = self._retrying("the keyframe store", StoreUnavailableError,
                                   functools.partial(open_store, self._db_url,
                                                     password=self._db_password))
            stack.callback(store.close)
            retention_s = None if self._retention is None else self._retention.retention_s
            if retention_s is not None and self._retention is not None:
                job = ImageRetention(store, retention_s, self._retention.image_retention_check_s,
                                     telemetry=self._telemetry)
                job.start()
                stack.callback(job.stop)
            objects = ObjectMap(store)
            # Ingest hands each keyframe it stored, decoded, to the mapping stage while one runs
            # here (``server/decoded.py``; the writer-lease role switches it).
            decoded = None if self._pipeline_factory is None else DecodedCache(active=False)
            ingest: Ingest | None = None
            corrections: CorrectionPublisher | None = None
            router_connected: Callable[[], bool] | None = None
            if self._connect is not None:
                session = self._retrying(f"a zenoh router at {', '.join(self._connect)}", ZenohSessionError,
                                         functools.partial(open_session, self._connect, self._zenoh_options))
                stack.callback(session.close)  # after ingest and map service undeclared theirs
                router_connected = functools.partial(has_router, session)
                ingest = Ingest(session, store, telemetry=self._telemetry, decoded=decoded)
                ingest.start()
                stack.callback(ingest.stop)
                mapserve = MapServe(session, objects)
                mapserve.start()
                stack.callback(mapserve.stop)
                corrections = CorrectionPublisher(session)
                corrections.load(store.session_anchors())
                stack.callback(corrections.close)
                log.info("zenoh session via %s: ingest and map service", ", ".join(self._connect))
            mapping = None
            if decoded is not None:
                build = functools.partial(self._make_pipeline, store, objects, decoded, corrections)
                mapping = MappingRole(store.writer_lease(self.name), build, on_running=decoded.set_active)
                mapping.start()
                stack.callback(mapping.stop)
            workers = None
            if self._workers_factory is not None:
                workers = self._workers_factory(self._db_url, self._db_password, self.name)
                workers.start()
                stack.callback(workers.stop)
            self._running = stack.pop_all()
        self._services = Services(store=store, objects=objects, ingest=ingest, mapping=mapping,
                                  router_connected=router_connected, telemetry=self._telemetry,
                                  workers=workers)
        return self._services

    def _make_pipeline(self, store: MapStore, objects: ObjectMap, decoded: DecodedCache,
                       corrections: CorrectionPublisher | None) -> MapPipeline:
        """A new mapping stage (the writer lease's holder runs it) taking ingest's decoded
        keyframes and publishing corrections."""
        if self._pipeline_factory is None:
            raise ServerError("this server has no mapping stage")
        pipeline = self._pipeline_factory(store, objects, decoded)
        if corrections is not None:
            pipeline.backend.set_publish(corrections.publish_anchor)
        return pipeline

    def _retrying(self, what: str, transient: type[Exception], attempt: Callable[[], T]) -> T:
        """``attempt()``; while it raises ``transient`` and ``retry_until`` is given and not set,
        log one warning and try again after a capped, doubling wait."""
        delay, n = RETRY_FIRST_S, 1
        while True:
            try:
                return attempt()
            except transient as exc:
                if self._retry_until is None:
                    raise
                log.warning("waiting for %s (attempt %d failed: %s); next attempt in %.0f s",
                            what, n, exc, delay)
                if self._retry_until.wait(delay):
                    self._cancelled = True
                    raise ServerError(f"stopped while waiting for {what}") from exc
                delay, n = min(2.0 * delay, RETRY_MAX_S), n + 1

    def stop(self) -> None:
        """Stop the mapping stage, the map service and the ingest, close the session, then the
        store (idempotent)."""
        running, self._running = self._running, None
        self._services = None
        if running is not None:
            running.close()

    @classmethod
    def from_config(
        cls, db_url: str, *, connect: Sequence[str] | None, config_path: str | None = None,
        require_tokens: bool = True, retry_until: threading.Event | None = None,
        zenoh_options: ZenohOptions | None = None, db_password: str | None = None,
        name: str | None = None, perception_workers: int | None = None,
    ) -> MapServer:
        """The server ``wardmap server`` runs, with its mapping stage configured from a file.

        Args:
            db_url, connect, require_tokens, retry_until, zenoh_options, db_password, name: as in
                the constructor.
            config_path: TOML file with ``[pipeline]``, ``[perception]`` and ``[association]``
                tables (defaults when None; ``deploy/server.toml``). With ``[pipeline]
                enabled = false`` keyframes are stored but not mapped.
            perception_workers: overrides ``[mapping] perception_workers`` (worker processes
                on this server, ``server/mapping/workers.py``).

        Raises:
            ConfigError: a bad file or value, or a bad endpoint.
            WardmapError: the segmentation model cannot be loaded (checked now, before
                anything starts).
        """
        from wardmap.server.association.associator import AssociationConfig
        from wardmap.server.backend.core import BackendConfig
        from wardmap.server.backend.stage import BackendStage
        from wardmap.server.mapping import MapPipeline, PipelineConfig
        from wardmap.server.mapping.workers import MappingConfig, PerceptionWorkers
        from wardmap.server.perception.config import PerceptionConfig
        from wardmap.server.perception.models import make_segmenter
        from wardmap.shared.config import load_config

        pipeline_cfg = load_config(PipelineConfig, config_path, section="pipeline")
        perception_cfg = load_config(PerceptionConfig, config_path, section="perception")
        association_cfg = load_config(AssociationConfig, config_path, section="association")
        backend_cfg = load_config(BackendConfig, config_path, section="backend")
        retention = load_config(RetentionConfig, config_path, section="store")
        mapping_cfg = load_config(MappingConfig, config_path, section="mapping")
        if perception_workers is not None:
            mapping_cfg = dataclasses.replace(mapping_cfg, perception_workers=perception_workers)
        telemetry = ServerTelemetry()
        if not pipeline_cfg.enabled:
            return cls(db_url, connect=connect, require_tokens=require_tokens, telemetry=telemetry,
                       retry_until=retry_until, zenoh_options=zenoh_options, db_password=db_password,
                       retention=retention, name=name)
        # Build the segmenter now: a missing or bad model is one clear error before anything starts.
        segmenter = make_segmenter(perception_cfg.segmenter, perception_cfg)

        def make_pipeline(store: MapStore, objects: ObjectMap, decoded: DecodedCache) -> MapPipeline:
            return MapPipeline(store, objects, config=pipeline_cfg, perception=perception_cfg,
                               association=association_cfg, segmenter=segmenter,
                               backend=BackendStage(store, backend_cfg, telemetry=telemetry, decoded=decoded,
                                                    nice=mapping_cfg.nice),
                               telemetry=telemetry, shared=mapping_cfg)

        def make_workers(url: str, password: str | None, server: str) -> PerceptionWorkers:
            return PerceptionWorkers(url, config=mapping_cfg, perception=perception_cfg, name=server,
                                     max_attempts=pipeline_cfg.max_attempts, password=password)

        return cls(db_url, connect=connect, pipeline_factory=make_pipeline, require_tokens=require_tokens,
                   telemetry=telemetry, retry_until=retry_until, zenoh_options=zenoh_options,
                   db_password=db_password, retention=retention, name=name,
                   workers_factory=make_workers if mapping_cfg.perception_workers > 0 else None)

    @property
    def start_cancelled(self) -> bool:
        """Whether ``start()`` gave up because ``retry_until`` was set while it waited."""
        return self._cancelled

    @property
    def services(self) -> Services | None:
        """The running parts, or None when the server is not started."""
        return self._services

    def __enter__(self) -> MapServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def default_name() -> str:
    """``HOST-PID``: this machine's name (printable ASCII, shortened) and this process's id."""
    host = "".join(c for c in socket.gethostname() if c.isascii() and c.isprintable() and c != " ")
    return f"{host[:MAX_HOLDER_LEN - 12] or 'server'}-{os.getpid()}"


def is_loopback(host: str) -> bool:
    """Whether every address ``host`` resolves to is a loopback address (False when it does not
    resolve)."""
    try:
        return _all_loopback(socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM))
    except OSError:
        return False


def _all_loopback(infos: Sequence[tuple[Any, ...]]) -> bool:
    return bool(infos) and all(ipaddress.ip_address(str(info[4][0]).partition("%")[0]).is_loopback
                               for info in infos)


def _bind(host: str, port: int, *, loopback_only: bool = False) -> socket.socket:
    """A listening TCP socket on ``host:port`` with ``TCP_NODELAY`` (accepted sockets inherit it:
    without it each keep-alive response waits on Nagle's algorithm, about 40 ms); ServerError
    when it cannot be bound, or when ``loopback_only`` and ``host`` is not a loopback address."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ServerError(f"bad HTTP port {port!r}: expected 0..65535")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, proto=socket.IPPROTO_TCP)
    except OSError as exc:
        raise ServerError(f"bad HTTP host {host!r}: {exc.strerror or exc}") from exc
    family, kind, proto, _, addr = infos[0]
    if loopback_only and not _all_loopback(infos):
        raise ServerError(
            f"--insecure-loopback refused on {host!r}: it serves the API without tokens, so only on a "
            "loopback address (127.0.0.1, ::1)"
        )
    # proto IPPROTO_TCP, not 0: asyncio sets TCP_NODELAY itself only on sockets that say TCP.
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.bind(addr)
        sock.listen(128)
    except OSError as exc:
        sock.close()
        reason = "address already in use" if exc.errno == 98 else (exc.strerror or str(exc))
        raise ServerError(f"cannot listen on http://{host}:{port}: {reason}") from exc
    sock.set_inheritable(True)
    return sock


@contextmanager
def _uvicorn_thread(
    server: Any, sock: socket.socket, done: threading.Event, stop: threading.Event
) -> Iterator[threading.Thread]:
    """Run ``server`` on a thread; ``done`` and ``stop`` are set when it ends for any reason."""

    def serve() -> None:
        try:
            server.run(sockets=[sock])
        except SystemExit:  # uvicorn exits this way when the lifespan start-up fails
            if not stop.is_set():  # set: stopped on purpose while the start-up waited
                log.error("HTTP server start-up failed")
        finally:
            done.set()
            stop.set()

    thread = threading.Thread(target=serve, name="wardmap-http", daemon=True)
    thread.start()
    try:
        yield thread
    finally:
        server.should_exit = True
        thread.join(SHUTDOWN_TIMEOUT_S)
        if thread.is_alive():
            log.warning("HTTP server did not stop within %.0f s", SHUTDOWN_TIMEOUT_S)


def run_server(
    connect: Sequence[str],
    db_url: str,
    http_host: str,
    http_port: int,
    *,
    stop: threading.Event | None = None,
    on_ready: Callable[[str], None] | None = None,
    config_path: str | None = None,
    insecure_loopback: bool = False,
    zenoh_options: ZenohOptions | None = None,
    db_password: str | None = None,
    name: str | None = None,
    perception_workers: int | None = None,
) -> None:
    """Serve until ``stop`` is set or SIGTERM/SIGINT (in the main thread).

    Args:
        connect: zenoh router endpoints ``tcp/HOST:PORT`` or ``tls/HOST:PORT`` the ingest
            connects to.
        db_url: keyframe store URL, ``sqlite:///PATH`` or ``postgresql://USER@HOST:PORT/DB``.
        http_host, http_port: where the REST API listens (port 0: any free port).
        stop: event that ends the server when set.
        on_ready: called once with the API's base URL ``http://HOST:PORT`` after the store
            is open, the ingest is subscribed and the HTTP socket accepts requests.
        config_path: TOML file with ``[pipeline]``, ``[perception]`` and ``[association]``
            tables (defaults when None; ``deploy/server.toml``).
        insecure_loopback: serve every route without a token; refused unless ``http_host``
            is a loopback address (the demo's mode).
        zenoh_options: TLS files and zenoh config file of the session (docs/security.md).
        db_password: the PostgreSQL password (see :class:`MapServer`).
        name: this server's name in the writer lease (see :class:`MapServer`).
        perception_workers: overrides ``[mapping] perception_workers`` (see
            :meth:`MapServer.from_config`).

    Raises:
        ConfigError: a bad zenoh endpoint, zenoh config file or TLS file.
        StoreError: the store URL or file is bad.
        ServerError: the HTTP port cannot be bound (or ``insecure_loopback`` off loopback),
            or start-up failed (see the log).
    """
    import asyncio

    import uvicorn

    from wardmap.server.http_limits import (
        LIMIT_CONCURRENCY,
        NOISY_MESSAGES,
        ThrottledLog,
        connection_cap,
        guarded_protocol,
        throttled_exception_handler,
    )

    check_session_config(connect, zenoh_options)  # endpoints, TLS files: one clear line, before start
    stop = stop if stop is not None else threading.Event()
    server_root = MapServer.from_config(db_url, connect=connect, config_path=config_path,
                                        require_tokens=not insecure_loopback, retry_until=stop,
                                        zenoh_options=zenoh_options, db_password=db_password,
                                        name=name, perception_workers=perception_workers)
    try:
        open_store(db_url, password=db_password).close()  # validate URL and file now: one clear line
    except StoreUnavailableError as exc:  # may pass later: start() waits for it
        log.warning("keyframe store not available yet: %s", exc)
    started = threading.Event()
    done = threading.Event()  # set by a signal, by `stop`, or when the HTTP thread ends

    accept_errors = ThrottledLog()

    class _Server(uvicorn.Server):
        async def startup(self, sockets: list[socket.socket] | None = None) -> None:
            # A failed accept() (e.g. out of file descriptors) is logged once per interval.
            asyncio.get_running_loop().set_exception_handler(throttled_exception_handler(accept_errors))
            await super().startup(sockets)
            if not self.should_exit:
                started.set()
                done.set()

    # uvicorn's start-up runs the app's lifespan, which starts the root; on_ready comes after.
    app = server_root.app
    # Limits (server/http_limits.py): connections, concurrency, header and keep-alive timeouts.
    config = uvicorn.Config(
        app, log_config=None, access_log=False, lifespan="on", timeout_graceful_shutdown=5,
        http=guarded_protocol(cap := connection_cap()), limit_concurrency=min(LIMIT_CONCURRENCY, cap + 1),
        timeout_keep_alive=5,
    )
    noisy = ThrottledLog(messages=NOISY_MESSAGES)
    uvicorn_log = logging.getLogger("uvicorn.error")
    server = _Server(config)
    sock = _bind(http_host, http_port, loopback_only=insecure_loopback)
    bound_port = int(sock.getsockname()[1])
    url = f"http://{http_host}:{bound_port}"
    uvicorn_log.addFilter(noisy)

    def not_cancelled(record: logging.LogRecord) -> bool:  # a stop while waiting is no failure
        return not server_root.start_cancelled

    uvicorn_log.addFilter(not_cancelled)
    try:
        with on_stop_signals(stop.set, "the server"), _uvicorn_thread(server, sock, done, stop):
            done.wait()  # start-up finished or failed
            if not started.is_set() and server_root.start_cancelled:
                log.info("map server stopped before it was ready")
                return
            if not started.is_set():
                raise ServerError(f"map server failed to start on {url} (see the log above)")
            log.info("map server ready at %s, ingest via %s", url, ", ".join(connect))
            if insecure_loopback:
                log.warning("REST API without tokens (--insecure-loopback): anyone on this host can read it")
            if on_ready is not None:
                on_ready(url)
            stop.wait()
            log.info("stopping map server")
    finally:
        uvicorn_log.removeFilter(noisy)
        uvicorn_log.removeFilter(not_cancelled)
        sock.close()
    log.info("map server stopped")
