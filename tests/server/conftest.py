"""Fixtures shared by the server's tests."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest
from procs import free_port


@pytest.fixture
def router() -> Iterator[str]:
    """A zenoh router (``run_router``) on a worker thread, on a free loopback port, once it is
    ready; yields its endpoint ``tcp/127.0.0.1:PORT`` and stops it afterwards."""
    pytest.importorskip("zenoh")
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

    worker = threading.Thread(target=target, daemon=True)
    worker.start()
    try:
        assert ready.wait(15) and not errors, errors
        yield endpoint
    finally:
        stop.set()
        worker.join(10)
