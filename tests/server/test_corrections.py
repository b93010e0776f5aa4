"""Tests of the server's correction publisher (``wardmap.server.corrections``) on loopback.

A real zenoh router runs on a thread (free port, shared memory and multicast scouting off); the
publisher's session (the server's ``open_session``) and this test's client session connect to it.
The tests wait on subscriber queues, matching status and zenoh replies with timeouts, never on
sleeps.
"""

from __future__ import annotations

import json
import queue
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from peers import matched_publisher  # noqa: E402  (after the importorskip guard)

from wardmap.server.corrections import CorrectionError, CorrectionPublisher  # noqa: E402
from wardmap.server.zenoh_session import open_session  # noqa: E402
from wardmap.shared.errors import ConfigError, WireError  # noqa: E402
from wardmap.shared.robotwire import CorrectionMsg, decode_correction  # noqa: E402
from wardmap.shared.se3 import yaw_transform  # noqa: E402
from wardmap.shared.zenoh_config import ALL_CORRECTIONS, client_config, correction_key  # noqa: E402

pytestmark = pytest.mark.timeout(60)

TIMEOUT_S = 10.0
T_A = yaw_transform(1.0, 2.0, 0.3)
T_B = yaw_transform(-4.0, 0.5, -1.2, 0.05)


@pytest.fixture
def session(router: str) -> Iterator[Any]:
    """The server side's session, as the composition root opens it."""
    with open_session([router]) as s:
        yield s


@pytest.fixture
def corrections(session: Any) -> Iterator[CorrectionPublisher]:
    with CorrectionPublisher(session, clock=lambda: 1_700_000_000.0) as cp:
        yield cp


@pytest.fixture
def client(router: str) -> Iterator[Any]:
    with zenoh.open(zenoh.Config.from_json5(json.dumps(client_config([router])))) as s:
        yield s


def _get(client: Any, selector: str) -> list[CorrectionMsg]:
    """The corrections of every ok reply to ``selector`` (blocks until the query is finished)."""
    replies = list(client.get(selector, timeout=TIMEOUT_S))
    assert all(r.ok is not None for r in replies), [r.err.payload.to_bytes() for r in replies if r.err]
    out = []
    for r in replies:
        msg = decode_correction(r.ok.payload.to_bytes())
        assert str(r.ok.key_expr) == correction_key(msg.robot_id)
        out.append(msg)
    return out


def test_publish_reaches_the_robots_key(session: Any, corrections: CorrectionPublisher, client: Any) -> None:
    """A subscriber on robot r1's correction key receives every correction published for r1, in
    order, decoded to what ``publish`` returned; r2's correction does not reach it."""
    received: queue.Queue[bytes] = queue.Queue()
    with client.declare_subscriber(correction_key("r1"), lambda s: received.put(s.payload.to_bytes())):
        matched_publisher(session, correction_key("r1"), TIMEOUT_S).undeclare()  # r1's subscriber is known
        sent = [corrections.publish("r1", "s1", T_A, revision=0, anchored_to="r0/s0"),
                corrections.publish("r2", "s9", T_A, revision=0),
                corrections.publish("r1", "s1", T_B, revision=4)]
        got = [decode_correction(received.get(timeout=TIMEOUT_S)) for _ in range(2)]
    assert [(m.robot_id, m.session_id, m.revision, m.anchored_to) for m in got] == [
        ("r1", "s1", 0, "r0/s0"), ("r1", "s1", 4, None)]
    np.testing.assert_allclose(got[1].T_map_odom, T_B, atol=1e-12)
    assert got[0].stamp == sent[0].stamp == 1_700_000_000.0 and got[0].state == "anchored"
    assert received.empty()
    c = corrections.counters()
    assert (c.published, c.publish_failures) == (3, 0)


def test_queries_answer_the_latest(corrections: CorrectionPublisher, client: Any) -> None:
    """A query for a robot's session gets that session's latest revision; without a session the
    robot's most recently published one; a wildcard one per robot; an unknown robot or session
    no reply; a bad ``session_id`` a reply error."""
    corrections.publish("r1", "old", T_A, revision=7)
    corrections.publish("r1", "new", T_A, revision=0)
    corrections.publish("r1", "new", T_B, revision=1)
    corrections.publish("r2", "x", T_B, revision=2)
    key = correction_key("r1")
    [one] = _get(client, f"{key}?session_id=new")
    assert (one.session_id, one.revision) == ("new", 1)
    np.testing.assert_allclose(one.T_map_odom, T_B, atol=1e-12)
    assert [(m.session_id, m.revision) for m in _get(client, f"{key}?session_id=old")] == [("old", 7)]
    assert [(m.session_id, m.revision) for m in _get(client, key)] == [("new", 1)]
    assert sorted((m.robot_id, m.revision) for m in _get(client, ALL_CORRECTIONS)) == [("r1", 1), ("r2", 2)]
    assert _get(client, f"{key}?session_id=unknown") == []
    assert _get(client, correction_key("r3")) == []
    replies = list(client.get(f"{key}?session_id=bad%20id", timeout=TIMEOUT_S))
    assert len(replies) == 1 and replies[0].err is not None
    assert "session_id" in replies[0].err.payload.to_bytes().decode()
    c = corrections.counters()
    assert (c.queries, c.query_errors) == (6, 1)
    latest = corrections.latest("r1")
    assert latest is not None and (latest.session_id, latest.revision) == ("new", 1)
    assert corrections.latest("r1", "nope") is None and corrections.latest("r9") is None


def test_publish_refuses_bad_input_and_non_increasing_revisions(corrections: CorrectionPublisher) -> None:
    """A revision not above the session's latest raises CorrectionError and keeps the latest; bad
    fields raise WireError naming them; after close() publishing raises; close is idempotent."""
    corrections.publish("r1", "s1", T_A, revision=3)
    for revision in (3, 2):
        with pytest.raises(CorrectionError, match="does not increase"):
            corrections.publish("r1", "s1", T_B, revision=revision)
    latest = corrections.latest("r1", "s1")
    assert latest is not None and latest.revision == 3
    corrections.publish("r1", "s2", T_B, revision=0)  # revisions count per session
    bad: list[tuple[tuple[Any, ...], dict[str, Any], str]] = [
        (("bad id", "s3", T_A), {"revision": 0}, "robot_id"),
        (("r1", "s3", np.eye(4) * 2), {"revision": 0}, "T_map_odom"),
        (("r1", "s3", T_A), {"revision": -1}, "revision"),
        (("r1", "s3", T_A), {"revision": 0, "anchored_to": "no-slash"}, "anchored_to"),
    ]
    for args, kwargs, field in bad:
        with pytest.raises(WireError) as e:
            corrections.publish(*args, **kwargs)
        assert e.value.field == field
    corrections.close()
    corrections.close()
    with pytest.raises(CorrectionError, match="closed"):
        corrections.publish("r1", "s1", T_A, revision=10)


def test_bad_capacity_is_refused(session: Any) -> None:
    with pytest.raises(ConfigError, match="capacity"):
        CorrectionPublisher(session, capacity=0)
