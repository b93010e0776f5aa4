"""Run the map server: keyframe ingest + REST API until SIGTERM/SIGINT or ``stop``.

:func:`run_server` checks what a user can get wrong up front (the store URL, the HTTP port)
so those fail with one clear :class:`ServerError`/:class:`StoreError`, then runs uvicorn on a
helper thread. The app's lifespan (:func:`wardmap.server.api.create_app`) opens the store and
starts the :class:`~wardmap.server.ingest.Ingest`; the main thread handles the signals and
waits on one event that either a signal, the caller's ``stop`` or the end of the HTTP
thread sets.
"""

from __future__ import annotations

import logging
import socket
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from wardmap.server.ingest import Ingest
from wardmap.server.mapserve import MapServe
from wardmap.server.objectmap import ObjectMap
from wardmap.server.store import KeyframeStore, open_store
from wardmap.shared.errors import WardmapError
from wardmap.shared.signals import on_stop_signals
from wardmap.shared.zenoh_config import client_config

log = logging.getLogger(__name__)

__all__ = ["ServerError", "run_server"]

SHUTDOWN_TIMEOUT_S = 15.0


class ServerError(WardmapError):
    """The map server cannot start (port in use, bad address, start-up failure)."""


def _bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port``; ServerError when it cannot be bound."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ServerError(f"bad HTTP port {port!r}: expected 0..65535")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError as exc:
        raise ServerError(f"bad HTTP host {host!r}: {exc.strerror or exc}") from exc
    family, _, _, _, addr = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
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
) -> None:
    """Serve until ``stop`` is set or SIGTERM/SIGINT (in the main thread).

    Args:
        connect: zenoh router endpoints ``tcp/HOST:PORT`` the ingest connects to.
        db_url: keyframe store URL, ``sqlite:///PATH``.
        http_host, http_port: where the REST API listens (port 0: any free port).
        stop: event that ends the server when set.
        on_ready: called once with the API's base URL ``http://HOST:PORT`` after the store
            is open, the ingest is subscribed and the HTTP socket accepts requests.
        config_path: TOML file with ``[pipeline]``, ``[perception]`` and ``[association]``
            tables (defaults when None; ``deploy/server.toml``).

    Raises:
        ConfigError: a bad zenoh endpoint.
        StoreError: the store URL or file is bad.
        ServerError: the HTTP port cannot be bound, or start-up failed (see the log).
    """
    import uvicorn

    from wardmap.server.api import create_app
    from wardmap.server.association.associator import AssociationConfig
    from wardmap.server.perception.models import PerceptionConfig, make_segmenter
    from wardmap.server.pipeline import MapPipeline, PipelineConfig
    from wardmap.shared.config import load_config

    client_config(connect)  # validate the endpoints before anything starts
    pipeline_cfg = load_config(PipelineConfig, config_path, section="pipeline")
    perception_cfg = load_config(PerceptionConfig, config_path, section="perception")
    association_cfg = load_config(AssociationConfig, config_path, section="association")
    # Build the segmenter now: a missing or bad model is one clear error before anything starts.
    segmenter = make_segmenter(perception_cfg.segmenter, perception_cfg) if pipeline_cfg.enabled else None
    open_store(db_url).close()  # validate URL and file here, so the error is one clear line
    stop = stop if stop is not None else threading.Event()
    started = threading.Event()
    done = threading.Event()  # set by a signal, by `stop`, or when the HTTP thread ends

    def make_ingest(store: KeyframeStore) -> Ingest:
        return Ingest(connect, store)

    def make_mapserve(objects: ObjectMap) -> MapServe:
        return MapServe(connect, objects)

    class _Server(uvicorn.Server):
        async def startup(self, sockets: list[socket.socket] | None = None) -> None:
            await super().startup(sockets)
            if not self.should_exit:
                started.set()
                done.set()

    def make_pipeline(store: Any, objects: ObjectMap) -> MapPipeline:
        return MapPipeline(store, objects, config=pipeline_cfg, perception=perception_cfg,
                           association=association_cfg, segmenter=segmenter)

    app = create_app(db_url, ingest_factory=make_ingest, mapserve_factory=make_mapserve,
                     pipeline_factory=make_pipeline if pipeline_cfg.enabled else None)
    config = uvicorn.Config(
        app, log_config=None, access_log=False, lifespan="on", timeout_graceful_shutdown=5
    )
    server = _Server(config)
    sock = _bind(http_host, http_port)
    bound_port = int(sock.getsockname()[1])
    url = f"http://{http_host}:{bound_port}"
    try:
        with on_stop_signals(stop.set, "the server"), _uvicorn_thread(server, sock, done, stop):
            done.wait()  # start-up finished or failed
            if not started.is_set():
                raise ServerError(f"map server failed to start on {url} (see the log above)")
            log.info("map server ready at %s, ingest via %s", url, ", ".join(connect))
            if on_ready is not None:
                on_ready(url)
            stop.wait()
            log.info("stopping map server")
    finally:
        sock.close()
    log.info("map server stopped")
