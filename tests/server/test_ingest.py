"""Keyframe ingest (``server/ingest.py``) pieces that need no Zenoh; the whole path runs in
``tests/integration/test_ingest.py``."""

from __future__ import annotations

from wardmap.server.ingest import wire_reason


def test_wire_rejection_reasons_are_bounded() -> None:
    """Rejection reasons come from a fixed set of top-level fields, whatever field name a
    hostile payload carries (each reason becomes a DB row and a Prometheus label)."""
    assert wire_reason("") == "wire: payload"
    assert wire_reason("keypoints.uv") == "wire: keypoints"
    assert wire_reason("T_odom_camera.q_xyzw") == "wire: T_odom_camera"
    reasons = {wire_reason(f"field{i}") for i in range(1000)} | {wire_reason("intrmnsics.fx")}
    assert reasons == {"wire: unknown field"}
