"""The live simulated source: same frames as ``wardmap sim`` writes, spec parsing, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from procs import one_line_error, wardmap

from wardmap.shared.dataset import DatasetReader
from wardmap.shared.errors import SimulationError
from wardmap.sim.live import LiveRun, SimSource, is_sim_source
from wardmap.sim.runner import generate


def test_live_frames_equal_written_frames(tmp_path: Path) -> None:
    """Frame i of a LiveRun is the frame generate() writes (PNG round trip: rgb, depth mm, labels)."""
    generate("two_robots", 2, tmp_path, frames=3)
    reader = DatasetReader(tmp_path / "robot_1")
    live = LiveRun("two_robots", 2, "robot_1", frames=3)
    assert len(live) == len(reader) == 3
    np.testing.assert_array_equal(live.stamps, reader.stamps)
    for i in (0, 1, 2, 0):  # out of order: re-renders from the start
        a, b = live.frame(i), reader.frame(i)
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.labels, b.labels)
        np.testing.assert_allclose(a.depth_m, b.depth_m, atol=1.01 / 5000)
        assert a.T_world_camera is not None and b.T_world_camera is not None
        np.testing.assert_allclose(a.T_world_camera, b.T_world_camera, atol=1e-6)
    odo = reader.odometry()
    assert odo is not None
    np.testing.assert_allclose(live.odometry()[1], odo[1], atol=1e-6)
    assert live.objects()["objects"] == reader.objects()["objects"]  # type: ignore[index]


@pytest.mark.parametrize(
    ("spec", "want"),
    [
        ("sim:aisle_slow_1", SimSource("aisle_slow_1", 0, None)),
        ("sim:ward_chairs:7", SimSource("ward_chairs", 7, None)),
        ("sim:two_robots:0:robot_1", SimSource("two_robots", 0, "robot_1")),
    ],
)
def test_spec_parses(spec: str, want: SimSource) -> None:
    assert is_sim_source(spec)
    assert SimSource.parse(spec) == want


@pytest.mark.parametrize(
    ("spec", "needle"),
    [
        ("sim:", "bad simulated source"),
        ("sim:aisle_slow_1:x", "bad simulated source"),
        ("sim:nowhere", "unknown scenario"),
    ],
)
def test_bad_spec_names_the_problem(spec: str, needle: str) -> None:
    with pytest.raises(SimulationError, match=needle):
        SimSource.parse(spec)


def test_unknown_robot_and_bad_frames() -> None:
    with pytest.raises(SimulationError, match="has no robot"):
        LiveRun("aisle_slow_1", 0, "robot_7")
    with pytest.raises(SimulationError, match="positive"):
        LiveRun("aisle_slow_1", 0, frames=0)
    with pytest.raises(IndexError):
        LiveRun("aisle_slow_1", 0, frames=2).frame(2)


def test_odom_frame_in_the_world_is_the_start_of_the_base() -> None:
    """T_world_odom @ T_odom_base(t) follows the ground-truth base within odometry drift."""
    live = LiveRun("aisle_slow_1", 0, frames=20)
    _, T_odom_base = live.odometry()
    T_world_base_odo = live.T_world_odom() @ T_odom_base[0]
    T_world_cam0 = live.groundtruth()[1][0]
    T_world_base0 = T_world_cam0 @ np.linalg.inv(live.rig.T_base_rgb)
    np.testing.assert_allclose(T_world_base_odo[:2, 3], T_world_base0[:2, 3], atol=1e-6)
    np.testing.assert_allclose(T_world_base_odo[:2, :2], T_world_base0[:2, :2], atol=1e-2)


def test_rolling_shutter_bands_cover_every_row_once_around_the_stamp() -> None:
    """Under a rolling shutter each band of rows has its own instant, from about half a readout
    before the stamp (top) to half after (bottom), the middle row at the stamp; 0 is one band."""
    from wardmap.sim.sensors import SensorRig

    rig = SensorRig(rgb_readout_s=0.03)
    bands = rig.readout_bands()
    rows = [r for r0, r1, _ in bands for r in range(r0, r1)]
    assert rows == list(range(rig.rgb.height))
    offsets = np.array([dt for _, _, dt in bands])
    assert np.all(np.diff(offsets) > 0)
    assert offsets[0] == pytest.approx(-0.015, abs=0.001) and offsets[-1] == pytest.approx(0.015, abs=0.001)
    assert SensorRig().readout_bands() == [(0, rig.rgb.height, 0.0)]
    for bad in (-0.01, 0.5, float("nan")):
        with pytest.raises(SimulationError, match="rgb_readout_s"):
            SensorRig(rgb_readout_s=bad)
    one_line_error(wardmap("sim", "--scenario", "pan_in_place", "--out", "/nonexistent/x",
                           "--rgb-readout-ms", "-5"), "rgb_readout_s")
