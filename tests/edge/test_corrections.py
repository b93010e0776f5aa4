"""Tests of the robot's correction state (``wardmap.edge.corrections.Corrections``): what it
applies, what it refuses and under which reason, and the map poses and numbers it reports.
The agent over real zenoh: tests/integration/test_corrections.py."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from factories import mutate, random_pose

from wardmap.edge.corrections import REJECT_REASONS, Corrections
from wardmap.shared.robotwire import CorrectionMsg, encode_correction
from wardmap.shared.se3 import make_transform, yaw_rotation, yaw_transform

T0 = 1_700_000_000.0
SESSION = "s-now"
T_MAP_ODOM = yaw_transform(10.0, -3.0, math.radians(90.0), 0.0)


def _payload(revision: int, *, robot: str = "r1", session: str = SESSION, T: np.ndarray = T_MAP_ODOM,
             stamp: float = T0) -> bytes:
    msg = CorrectionMsg(robot, session, revision, stamp + revision, T, anchored_to="r0/s0")
    return encode_correction(msg)


def test_a_correction_of_the_running_session_is_applied() -> None:
    """A valid correction for this robot's running session is applied: anchored, its T_map_odom
    held, map poses are T_map_odom @ T_odom_x, the summary and heartbeat numbers say so."""
    c = Corrections("r1")
    assert not c.anchored and c.T_map_odom is None and c.map_pose(np.eye(4)) is None
    assert c.stats(T_odom_base=np.eye(4)) == {"anchored": 0, "corrections": 0, "bad_corrections": 0}
    assert c.handle(_payload(0), SESSION)
    assert c.anchored and c.current is not None and c.current.anchored_to == "r0/s0"
    T_odom_base = yaw_transform(1.0, 0.0, math.radians(30.0))
    np.testing.assert_allclose(c.map_pose(T_odom_base), T_MAP_ODOM @ T_odom_base, atol=1e-12)
    stats = c.stats(T_odom_base=T_odom_base)
    assert stats == {"anchored": 1, "corrections": 1, "bad_corrections": 0,
                     "map_x": 10.0, "map_y": -2.0, "map_z": 0.0, "map_yaw_deg": 120.0}
    summary = c.summary(T_odom_base=T_odom_base)
    assert summary == {"anchored": True, "correction_revision": 0, "anchored_to": "r0/s0", "corrections": 1,
                       "duplicate_corrections": 0, "bad_corrections": {},
                       "map_pose": {"x": 10.0, "y": -2.0, "z": 0.0, "yaw_deg": 120.0}}


def test_newer_revisions_replace_and_duplicates_are_no_error() -> None:
    """Revisions 0, 2, 5 are applied in turn (gaps are fine); the same message again (subscription
    and query both deliver it) is a duplicate: not applied, not refused."""
    c = Corrections("r1")
    moved = yaw_transform(11.0, -3.0, 0.0)
    assert c.handle(_payload(0), SESSION)
    assert c.handle(_payload(2), SESSION)
    assert not c.handle(_payload(2), SESSION)
    assert c.handle(_payload(5, T=moved), SESSION)
    assert c.current is not None and c.current.revision == 5
    np.testing.assert_allclose(c.T_map_odom, moved, atol=1e-12)
    assert c.summary()["duplicate_corrections"] == 1 and c.rejections() == {}
    assert c.stats()["corrections"] == 3


def test_refusals_are_counted_by_reason_and_never_raise() -> None:
    """Stale revisions, the same revision with another pose, other robots, other sessions and
    garbage are refused with their reason; the held correction stays; nothing raises."""
    c = Corrections("r1")
    assert c.handle(_payload(4), SESSION)
    refused = {
        "stale": [_payload(3), _payload(0), _payload(4, T=np.eye(4))],
        "other_robot": [_payload(9, robot="r2")],
        "other_session": [_payload(9, session="yesterday"), _payload(0, session="yesterday")],
        "undecodable": [b"", b"\xc1", b"garbage" * 10, _payload(5)[:-4], msgpack.packb({"schema": "x"}),
                        bytes(5000), "not bytes"],
    }
    for reason, payloads in refused.items():
        for p in payloads:
            assert not c.handle(p, SESSION), reason
    assert c.rejections() == {reason: len(p) for reason, p in refused.items()}
    assert set(c.rejections()) <= set(REJECT_REASONS)
    assert c.stats()["bad_corrections"] == sum(len(p) for p in refused.values())
    assert c.current is not None and c.current.revision == 4
    np.testing.assert_allclose(c.T_map_odom, T_MAP_ODOM, atol=1e-12)


def test_fuzzed_payloads_never_raise() -> None:
    """300 seeded mutations of a valid correction: handle returns a bool and any refusal is counted
    under a reason of the fixed vocabulary."""
    rng = np.random.default_rng(3)
    c = Corrections("r1")
    base = _payload(1, T=random_pose(rng))
    for _ in range(300):
        assert isinstance(c.handle(mutate(base, rng, random_payloads=True), SESSION), bool)
    assert set(c.rejections()) <= set(REJECT_REASONS) and c.rejections().get("undecodable", 0) > 150


def test_prior_gives_map_poses_until_a_correction_replaces_it() -> None:
    """With a --map-pose prior the map pose is known but the session is not anchored; the first
    correction replaces the prior. Without odometry the camera's pose is used, its heading being
    that of its optical (z) axis."""
    prior = yaw_transform(1.0, 2.0, 0.0)
    c = Corrections("r1", T_map_odom_prior=prior)
    R_odom_level_camera = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # looks along +x
    T_odom_camera = make_transform(yaw_rotation(math.radians(45.0)) @ R_odom_level_camera, [0.5, 0.0, 1.2])
    stats = c.stats(T_odom_camera=T_odom_camera)
    assert stats["anchored"] == 0
    assert (stats["map_x"], stats["map_y"], stats["map_z"]) == (1.5, 2.0, 1.2)
    assert stats["map_yaw_deg"] == pytest.approx(45.0)
    assert c.handle(_payload(0), SESSION)
    assert c.stats(T_odom_camera=T_odom_camera)["anchored"] == 1
    np.testing.assert_allclose(c.map_pose(np.eye(4)), T_MAP_ODOM, atol=1e-12)
    assert c.stats(T_odom_base=np.eye(4), T_odom_camera=T_odom_camera)["map_yaw_deg"] == 90.0  # base first
