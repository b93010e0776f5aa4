"""The edge agent (``wardmap.edge.agent``) in this process: its configuration (the example file,
validation of every budget setting), what its constructor refuses before opening anything, and
a run against a router on a thread with an acker standing in for the server (``peers``).
``wardmap edge`` as a process: tests/integration/test_edge_cmd.py.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from wardmap.edge.agent import AgentConfig, EdgeAgent
from wardmap.edge.outbox import Outbox
from wardmap.shared.config import load_config
from wardmap.shared.errors import ConfigError, DatasetError


def test_example_config_matches_the_defaults() -> None:
    path = Path(__file__).resolve().parents[2] / "deploy" / "edge.toml"
    assert load_config(AgentConfig, path, section="agent") == AgentConfig()


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("depth_stride = 3", "depth_stride"),
        ("thermal_stride = 8", "thermal_stride"),
        ("thermal_every = -1", "thermal_every"),
        ("max_keypoints = -5", "max_keypoints"),
        ("thermal_unit_k = 0.0", "thermal_unit_k"),
        ("jpeg_quality = 0", "jpeg_quality"),
        ("label_threads = 0", "label_threads"),
        ("rate_hz = -1.0", "rate_hz"),
        ("correction_query_s = -1.0", "correction_query_s"),
        ("correction_query_s = inf", "correction_query_s"),
        ("jpg_quality = 80", "jpg_quality"),
    ],
)
def test_bad_agent_config_is_rejected(tmp_path: Path, text: str, needle: str) -> None:
    path = tmp_path / "edge.toml"
    path.write_text(f"[agent]\n{text}\n")
    with pytest.raises(ConfigError, match=needle):
        load_config(AgentConfig, path, section="agent")


@pytest.mark.parametrize(
    ("robot", "source", "connect", "error", "needle"),
    [
        ("bad id!", "{dataset}", ["tcp/127.0.0.1:7447"], ConfigError, "robot"),
        ("r1", "{dataset}", ["tcp/nohost"], ConfigError, "nohost"),
        ("r1", "{dataset}", [], ConfigError, "at least one --connect"),
        ("r1", "{missing}", ["tcp/127.0.0.1:7447"], DatasetError, "is not a folder"),
    ],
)
def test_constructor_refuses_bad_input_before_opening_anything(
        tmp_path: Path, robot: str, source: str, connect: list[str], error: type[Exception], needle: str,
) -> None:
    """A bad robot id, endpoint, no endpoint or a missing data-set folder raise at construction;
    no outbox file is made."""
    dataset = tmp_path / "dataset"
    dataset.mkdir()
    outbox = tmp_path / "outbox" / "outbox.sqlite"
    with pytest.raises(error, match=needle):
        EdgeAgent(robot, source.format(dataset=dataset, missing=tmp_path / "nope"), connect, outbox)
    assert not outbox.parent.exists()


@pytest.mark.timeout(120)
def test_rejected_keyframes_leave_the_outbox_and_are_counted_by_reason(tmp_path: Path) -> None:
    """Four simulated frames (aisle_slow_1, seed 0) through the agent, every keyframe acked
    ``rejected``: each arrives once, none is resent, the summary counts them under the server's
    reason, and the outbox ends empty (resending a payload the server refused is pointless)."""
    pytest.importorskip("zenoh")
    from peers import Acker, router_on_thread

    from wardmap.sim.live import LiveRun

    path = tmp_path / "outbox.sqlite"
    config = AgentConfig(max_frames=4, flush_timeout_s=20.0, privacy="off")
    with router_on_thread() as endpoint, Acker(endpoint, "rejected", "depth: corrupt") as acker:
        summary: dict[str, Any] = EdgeAgent("r1", LiveRun("aisle_slow_1", 0), [endpoint], path,
                                            config=config).run()
    received = acker.received  # the acker's worker has stopped
    n = summary["keyframes"]
    assert summary["frames"] == 4 and n >= 1
    assert sorted(received) == [(summary["session_id"], seq) for seq in range(n)]
    assert summary["rejected"] == {"depth: corrupt": n}
    assert summary["acked"] == 0 and summary["resent"] == 0
    assert summary["pending"] == 0 and summary["flushed"] is True
    with Outbox.open(path) as outbox:
        assert len(outbox) == 0


@pytest.mark.timeout(120)
@pytest.mark.parametrize("drop_when_behind", [True, False])
def test_a_stream_that_drops_frames_warms_the_tracker_up_first(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, drop_when_behind: bool
) -> None:
    """A source whose frames are lost when the tracker is behind (a camera, or a replay told to
    behave like one) has the tracker's kernels readied before the first frame; a replay that
    waits for the tracker does not pay for it."""
    pytest.importorskip("zenoh")
    from peers import Acker, router_on_thread

    from wardmap.sim.live import LiveRun

    config = AgentConfig(max_frames=2, flush_timeout_s=20.0, privacy="off", drop_when_behind=drop_when_behind)
    with (
        caplog.at_level("INFO", logger="wardmap.edge.agent"),
        router_on_thread() as endpoint,
        Acker(endpoint),
    ):
        agent = EdgeAgent("r1", LiveRun("aisle_slow_1", 0), [endpoint], tmp_path / "o.sqlite", config=config)
        summary = agent.run()
    assert summary["frames"] + summary.get("frames_dropped", 0) >= 1
    warmed = [r.getMessage() for r in caplog.records if "tracker kernels ready" in r.getMessage()]
    assert len(warmed) == (1 if drop_when_behind else 0), warmed
