"""Fixtures shared by the server's tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest


@pytest.fixture
def router() -> Iterator[str]:
    """A zenoh router on a worker thread on a free loopback port (``peers.router_on_thread``);
    yields its endpoint once it is ready."""
    pytest.importorskip("zenoh")
    from peers import router_on_thread

    with router_on_thread() as endpoint:
        yield endpoint
