"""``wardmap edge`` as a daemon on a live source: a ROS 2 robot's topics over Zenoh (``ros2:``).

A robot (``ros2robot.Robot``: CDR messages on rmw_zenoh keys, a client of a real router
subprocess) publishes a simulated sequence's colour, depth and wheel odometry, pauses longer than
the source's ``ros_stall_s`` (the camera "unplugged") and goes on. The agent, a subprocess,
tracks it, reconnects, reports it in its heartbeat and summary, and records what it saw
(``--record``); ``wardmap track`` then replays the recording.
"""

from __future__ import annotations

import contextlib
import json
import queue
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from peers import Acker, open_client
from procs import child_env, read_line, router_process, wardmap, wardmap_cmd
from procs import stop as stop_proc

pytest.importorskip("zenoh")
pytest.importorskip("rosbags", reason="the ros extra (rosbags) is not installed")

from ros2robot import Robot, camera_info, image, odometry

from wardmap.shared.dataset import DatasetReader
from wardmap.shared.wire import decode_heartbeat
from wardmap.shared.zenoh_config import heartbeat_key

pytestmark = [pytest.mark.integration, pytest.mark.timeout(150)]

TIMEOUT_S = 60.0
FRAMES = 30
PAUSE_AFTER = 15  # frames before the robot's camera goes away for 4 s (ros_stall_s = 1.5)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from wardmap.sim.runner import generate

    path = tmp_path_factory.mktemp("live") / "aisle"
    generate("aisle_slow_1", 0, path, frames=FRAMES)
    return path


def _publish(bot: Robot, reader: DatasetReader, go: threading.Event, done: threading.Event) -> None:
    """CameraInfo every 50 ms from the start (a camera driver); after ``go``, the frames at 10 Hz
    with the odometry around them, a 4 s gap after frame PAUSE_AFTER; then ``done``."""
    info = camera_info(reader.calibration.rgb)
    while not go.wait(0.05):
        bot.put("/camera/color/camera_info", info)
    odo = reader.odometry()
    assert odo is not None
    stamps, poses = odo
    k = 0
    for i in range(len(reader)):
        frame = reader.frame(i)
        while k < len(stamps) and stamps[k] <= frame.stamp + 0.05:
            bot.put("/odom", odometry(float(stamps[k]), poses[k]))
            k += 1
        bot.put("/camera/color/camera_info", info)
        bot.put("/camera/color/image_raw", image(frame.stamp, frame.rgb, "rgb8"))
        bot.put("/camera/aligned_depth_to_color/image_raw", image(frame.stamp, frame.depth_m, "32FC1"))
        if i == PAUSE_AFTER:
            done.wait(4.0)  # the camera is away (ros_stall_s = 1.5)
        else:
            done.wait(0.1)
    done.set()


def test_edge_daemon_on_ros2_topics_survives_a_gap_reports_and_records(
        dataset: Path, tmp_path: Path) -> None:
    config = tmp_path / "edge.toml"
    config.write_text("[source]\nros_stall_s = 1.5\n")
    rec = tmp_path / "rec"
    heartbeats: queue.Queue[bytes] = queue.Queue(maxsize=256)

    def on_heartbeat(sample: Any) -> None:
        with contextlib.suppress(queue.Full):
            heartbeats.put_nowait(sample.payload.to_bytes())

    reader = DatasetReader(dataset)
    go, done = threading.Event(), threading.Event()
    with router_process(15.0) as (_, router), Acker(router), \
            open_client(router) as watcher, watcher.declare_subscriber(heartbeat_key("r7"), on_heartbeat):
        bot = Robot(router)
        publisher = threading.Thread(target=_publish, args=(bot, reader, go, done), daemon=True)
        publisher.start()
        cmd = wardmap_cmd("edge", "--robot", "r7", "--source", f"ros2:{router}", "--connect", router,
                          "--outbox", str(tmp_path / "outbox"), "--config", str(config), "--privacy", "off",
                          "--calibration", str(dataset / "calibration.toml"), "--record", str(rec))
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env=child_env())
        try:
            assert proc.stdout is not None
            ready = read_line(proc.stdout, TIMEOUT_S)
            assert ready is not None and " ready: session " in ready, ready
            assert f"source ros2:{router}" in ready and "labels: NONE" in ready
            go.set()
            assert done.wait(TIMEOUT_S)
            last: dict[str, Any] = {}
            seen_back = False  # a heartbeat said: reconnected once, the source is up
            deadline = time.monotonic() + TIMEOUT_S  # then the asserts below say what was missing
            while (not seen_back or last.get("received", 0) < FRAMES - 2) and time.monotonic() < deadline:
                with contextlib.suppress(queue.Empty):
                    last = dict(decode_heartbeat(heartbeats.get(timeout=1.0)).stats)
                    seen_back |= last["reconnects"] == 1 and last["source_up"] == 1
            proc.send_signal(signal.SIGTERM)
            out, err = proc.communicate(timeout=TIMEOUT_S)
        finally:
            stop_proc(proc)
            go.set()
            done.set()
            publisher.join(10)
            bot.session.close()
    assert proc.returncode == 0, err
    assert "no label source" in err and "lost (no images on /camera/color/image_raw for 1.5 s)" in err
    assert err.count("back after") == 1, (last, err)
    # the heartbeat: frames received / tracked / dropped, the reconnect, the pose in odom
    assert seen_back and last["reconnects"] == 1, last
    assert last["received"] >= FRAMES - 2  # all but the last pair (waiting for a later depth image)
    # a live source drops (counted) what the tracker cannot keep up with on this shared host
    assert last["tracked"] >= 5 and last["tracked"] + last["dropped"] <= last["received"]
    assert {"odom_x", "odom_y", "odom_z", "odom_yaw_deg"} <= set(last)
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["reconnects"] == 1
    # the subscription's own drops, counted in the heartbeat too (it came before the summary)
    assert 0 <= last["source_dropped"] <= summary["frames_source_dropped"]
    assert summary["frames_received"] >= FRAMES - 2  # the last pair may still wait for a later depth
    handled = summary["frames"] + summary["frames_dropped"] + summary["frames_late"]
    assert 0 <= summary["frames_received"] - handled <= 3  # the rest was in the slot at the stop
    assert summary["keyframes"] >= 2
    recorded = summary["recorded"]
    assert recorded["folder"] == str(rec) and recorded["frames"] == summary["frames_received"]
    replay = DatasetReader(rec)
    assert len(replay) == recorded["frames"] and replay.odometry() is not None
    assert replay.calibration.T_base_rgb is not None
    track = wardmap("track", str(rec), "--out", str(tmp_path / "traj.txt"), timeout_s=TIMEOUT_S)
    assert track.returncode == 0, track.stderr
    assert json.loads(track.stdout.strip().splitlines()[-1])["frames"] == recorded["frames"]
