"""The writer-lease role (server/mapping/role.py): the mapping stage runs only while the lease is
held, stops when it is lost, starts when it is taken over. The lease and the stage are fakes
here (the real lease on PostgreSQL: tests/server/store/test_postgres.py; two real servers:
tests/integration/test_multi_server.py)."""

from __future__ import annotations

import threading

import pytest

from wardmap.server.mapping.role import MappingRole
from wardmap.shared.errors import ConfigError

EVENT_TIMEOUT_S = 10.0


class _Lease:
    """A lease the test grants or takes away: ``free`` says whether acquire() gets it."""

    def __init__(self, free: bool) -> None:
        self.holder = "me"
        self.free = free
        self.mine = False
        self.other = "them"

    def acquire(self) -> bool:
        self.mine = self.mine or self.free
        return self.mine

    def held(self) -> bool:
        return self.mine

    def current_holder(self) -> str | None:
        return self.holder if self.mine else self.other

    def release(self) -> None:
        self.mine = False


class _Pipeline:
    def __init__(self, events: list[str], started: threading.Event, stopped: threading.Event,
                 fail: bool = False) -> None:
        self._events, self._started, self._stopped, self._fail = events, started, stopped, fail

    def start(self) -> None:
        if self._fail:
            raise ConfigError("no model")
        self._events.append("start")
        self._started.set()

    def stop(self) -> None:
        self._events.append("stop")
        self._stopped.set()

    alive = True

    def running(self) -> bool:
        return self.alive


def _role(lease: _Lease, events: list[str], fail: bool = False) -> tuple[MappingRole, threading.Event,
                                                                      threading.Event]:
    """A role over fake stages; ``events`` also gets ``running``/``idle`` from its on_running."""
    started, stopped = threading.Event(), threading.Event()
    role = MappingRole(lease, lambda: _Pipeline(events, started, stopped, fail),  # type: ignore[arg-type,return-value]
                       poll_s=0.01, on_running=lambda on: events.append("running" if on else "idle"))
    return role, started, stopped


def test_the_holder_runs_the_stage_until_it_loses_the_lease() -> None:
    """Granted at start: the stage starts with the role and the state says held by this server;
    the lease lost (its connection ended): the stage stops and the state names the other holder;
    the lease free again: a new stage starts; stop() stops it and gives the lease back."""
    lease, events = _Lease(free=True), []
    role, started, stopped = _role(lease, events)
    role.start()
    try:
        assert started.is_set() and role.pipeline is not None
        assert role.state().held and role.state().holder == "me" and role.running()
        started.clear()
        lease.free, lease.mine = False, False  # lost: another server takes it
        assert stopped.wait(EVENT_TIMEOUT_S)
        assert not started.is_set()
        lease.free = True
        assert started.wait(EVENT_TIMEOUT_S)
        assert events == ["running", "start", "stop", "idle", "running", "start"]
    finally:
        role.stop()
    assert events == ["running", "start", "stop", "idle", "running", "start", "stop", "idle"]
    assert not lease.mine and role.pipeline is None and not role.running()


def test_a_standby_serves_without_a_stage_and_takes_over() -> None:
    """Lease held elsewhere at start: no stage, the state names the holder; once the lease is free
    the role takes it and starts the stage."""
    lease, events = _Lease(free=False), []
    role, started, _ = _role(lease, events)
    role.start()
    try:
        assert role.pipeline is None and not role.state().held and role.state().holder == "them"
        lease.free = True
        assert started.wait(EVENT_TIMEOUT_S)
        assert role.state().held
    finally:
        role.stop()


def test_a_stage_that_cannot_start_gives_the_lease_back() -> None:
    """A stage failing at start (a bad model) propagates from start() and leaves the lease free
    for another server."""
    lease, events = _Lease(free=True), []
    role, _, _ = _role(lease, events, fail=True)
    with pytest.raises(ConfigError, match="no model"):
        role.start()
    assert not lease.mine and events == ["running", "idle"]


def test_a_holder_whose_stage_died_gives_the_lease_back() -> None:
    """The stage's thread died on the holder: the role stops it and releases the lease, so a
    standby (here: the same role, next round) starts a new stage."""
    lease, events = _Lease(free=True), []
    role, started, stopped = _role(lease, events)
    role.start()
    try:
        first = role.pipeline
        assert isinstance(first, _Pipeline)
        started.clear()
        first.alive = False
        assert stopped.wait(EVENT_TIMEOUT_S) and started.wait(EVENT_TIMEOUT_S)
        assert role.pipeline is not first
        assert events[:6] == ["running", "start", "stop", "idle", "running", "start"]
    finally:
        role.stop()
