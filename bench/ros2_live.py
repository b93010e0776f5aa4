"""Live ROS 2 source benchmark: a robot's camera topics over Zenoh at 30 Hz into the edge daemon.

Two processes, as on a robot. The *camera* process (this script with ``--camera``; pinned to
core 0 when the host has two) runs a Zenoh router on loopback (shared memory off), puts a data
set's frames (``--data``, default the TUM excerpt; 640x480 ``rgb8`` colour, ``32FC1`` depth,
CameraInfo) on rmw_zenoh keys at 30 Hz, CDR serialised at each tick as a camera driver does
(tests/ros2robot.py), each stamped with the host clock at its tick, and stands in for the map
server: it decodes every keyframe and acks it (no store). The *edge* process (this script;
pinned to the other core unless ``--no-pin``) runs the edge daemon
(:class:`wardmap.edge.agent.EdgeAgent`) on ``--source ros2:`` (reconnect loop, stream slot of
``--capacity``, drop-oldest), labels ``none``, privacy off, outbox on disk. Counts frames
published, received, tracked (a measured pose), dropped, late and lost before the stream; track
ms per frame; latency camera stamp -> tracked pose and camera stamp -> keyframe acked (ms, host
clock). A throwaway tracker first tracks a few frames untimed (numba compiles on first use).

    python bench/ros2_live.py [--data DIR] [--capacity N] [--no-pin] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the test robot (ros2robot)
import argparse
import json
import os
import queue
import subprocess
import tempfile
import threading
import time
from typing import Any

import _one_core  # noqa: F401  (one thread per library, before numba and OpenCV load)
import cv2
import numpy as np
from _report import git_rev, machine, publish, tracker_config

ROOT = Path(__file__).resolve().parents[1]
TUM = ROOT.parent / "shared" / "data" / "tum_fr1_rpy_s3_first100"
RATE_HZ = 30.0
WARM_UP_FRAMES = 5
TAIL_S = 1.0
"""The edge is stopped this long after the last frame was published."""


def pin(core: int) -> str:
    """Pin this process to ``core`` when the host has more than one; says what was done."""
    if (os.cpu_count() or 1) < 2 or not hasattr(os, "sched_setaffinity"):
        return "not pinned"
    os.sched_setaffinity(0, {core})
    return f"core {core}"


# --------------------------------------------------------------------------- camera process


def camera_main(core: int, data: Path) -> int:
    """Router + camera publisher + stand-in acker; talks to the edge over stdin/stdout lines."""
    if core >= 0:
        pin(core)
    from peers import open_client, router_on_thread
    from ros2robot import Robot, camera_info, image

    from wardmap.shared.dataset import DatasetReader
    from wardmap.shared.wire import AckMsg, decode_keyframe, encode
    from wardmap.shared.zenoh_config import ALL_KEYFRAMES, ack_key

    reader = DatasetReader(data)
    frames = [reader.frame(i) for i in range(len(reader))]
    acks: list[tuple[float, float]] = []  # (keyframe stamp, host time of its ack)
    inbox: queue.Queue[bytes | None] = queue.Queue(maxsize=256)

    def ack_worker(session: Any) -> None:
        while (payload := inbox.get()) is not None:
            msg = decode_keyframe(payload)
            ack = AckMsg(msg.robot_id, msg.session_id, msg.seq, "stored", "")
            session.put(ack_key(msg.robot_id), encode(ack))
            acks.append((msg.stamp, time.time()))

    with router_on_thread() as endpoint:
        bot = Robot(endpoint)
        server = open_client(endpoint)
        sub = server.declare_subscriber(ALL_KEYFRAMES, lambda s: inbox.put(s.payload.to_bytes()))
        worker = threading.Thread(target=ack_worker, args=(server,), daemon=True)
        worker.start()
        go = threading.Event()
        info = camera_info(reader.calibration.rgb)
        bot.keep_putting("/camera/color/camera_info", info, go)
        print(f"endpoint {endpoint}", flush=True)
        if sys.stdin.readline().strip() != "go":
            return 1
        go.set()
        t_next = time.time() + 0.2
        for f in frames:
            time.sleep(max(0.0, t_next - time.time()))
            stamp = round(t_next, 6)  # the exposure: the host clock at this tick
            bot.put("/camera/color/image_raw", image(stamp, f.rgb, "rgb8"))
            bot.put("/camera/aligned_depth_to_color/image_raw", image(stamp, f.depth_m, "32FC1"))
            t_next += 1.0 / RATE_HZ
        print("published", flush=True)
        sys.stdin.readline()  # the edge has flushed
        inbox.put(None)
        worker.join(10)
        sub.undeclare()
        server.close()
        bot.session.close()
    print(json.dumps({"published": len(frames), "acks": acks}), flush=True)
    return 0


# --------------------------------------------------------------------------- edge process


def edge_run(core: int | None, capacity: int, data: Path, tracker: Any = None) -> dict[str, Any]:
    """Start the camera process, run the edge daemon on its topics (pinned to ``core`` unless
    None; a stream slot of ``capacity`` frames; ``tracker``: its TrackerConfig, the default when
    None), return the figures."""
    where = pin(core) if core is not None else "not pinned"
    from wardmap.edge import agent as agent_mod
    from wardmap.edge.agent import AgentConfig, EdgeAgent
    from wardmap.edge.bag import BagSourceConfig
    from wardmap.edge.live import ReconnectingSource
    from wardmap.edge.ros2live import parse_spec, ros2_connector
    from wardmap.edge.tracker import Tracker, TrackInput, TrackResult
    from wardmap.shared.dataset import DatasetReader

    reader = DatasetReader(data)
    warm = Tracker(reader.calibration)  # numba compiles its kernels before the clock runs
    for i in range(WARM_UP_FRAMES):
        f = reader.frame(i)
        warm.track(TrackInput(f.stamp, f.rgb, f.depth_m, None, None))
    track_ms: list[float] = []
    track_cpu_ms: list[float] = []  # CPU time of the tracking thread: wall minus what others took
    pose_latency_ms: list[float] = []

    class TimedTracker(Tracker):  # the bench's probe: time each frame, age of its stamp at the pose
        def track(self, inp: TrackInput) -> TrackResult:
            t0, c0 = time.perf_counter(), time.thread_time()
            res = super().track(inp)
            track_ms.append((time.perf_counter() - t0) * 1e3)
            track_cpu_ms.append((time.thread_time() - c0) * 1e3)
            pose_latency_ms.append((time.time() - inp.stamp) * 1e3)
            return res

    agent_mod.Tracker = TimedTracker  # type: ignore[misc]
    cam_core = "-1" if core is None else str(1 - core)
    cam = subprocess.Popen([sys.executable, __file__, "--camera", cam_core, "--data", str(data)],
                           stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, text=True)
    assert cam.stdin is not None and cam.stdout is not None
    try:
        line = cam.stdout.readline().split()
        if len(line) != 2 or line[0] != "endpoint":
            raise RuntimeError(f"camera process did not start: {line}")
        endpoint = line[1]
        cfg = BagSourceConfig(odom_topic="", ros_stall_s=5.0)
        source = ReconnectingSource(ros2_connector(cfg, parse_spec(f"ros2:{endpoint}", cfg)))
        with tempfile.TemporaryDirectory() as tmp:
            agent = EdgeAgent("bench", source, [endpoint], Path(tmp) / "outbox.db",
                              config=AgentConfig(labels="none", privacy="off", flush_timeout_s=10.0,
                                                 stream_capacity=capacity),
                              tracker_config=tracker)

            def on_ready(_session: str, _pending: int) -> None:
                cam.stdin.write("go\n")  # type: ignore[union-attr]
                cam.stdin.flush()  # type: ignore[union-attr]

                def stop_after_last() -> None:
                    cam.stdout.readline()  # type: ignore[union-attr]  # "published"
                    time.sleep(TAIL_S)
                    agent.stop()

                threading.Thread(target=stop_after_last, daemon=True).start()

            summary = agent.run(on_ready=on_ready)
        cam.stdin.write("flushed\n")
        cam.stdin.flush()
        out = json.loads(cam.stdout.readline())
    finally:
        cam.wait(30)
    ack_ms = [(t - s) * 1e3 for s, t in out["acks"]]
    return {"where": where, "published": out["published"], "summary": summary, "track_ms": track_ms,
            "track_cpu_ms": track_cpu_ms,
            "pose_ms": pose_latency_ms, "ack_ms": ack_ms}


def pct(values: list[float]) -> str:
    if not values:
        return "-"
    return f"{np.median(values):.1f} / {np.percentile(values, 95):.1f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--write", type=Path, help="put the table into this BENCHMARKS.md")
    ap.add_argument("--data", type=Path, default=TUM, help="the data set the camera publishes, 640x480 "
                    "(default: the TUM excerpt)")
    ap.add_argument("--capacity", type=int, default=2, help="the edge's stream slot, frames (default 2, "
                    "the edge's default)")
    ap.add_argument("--no-pin", action="store_true", help="let the OS place both processes (a loaded host)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a [tracker] setting of the edge, e.g. sbi_scale=0 (repeatable)")
    ap.add_argument("--camera", type=int, metavar="CORE", help=argparse.SUPPRESS)  # the camera process
    args = ap.parse_args()
    if not (args.data / "rgb.txt").is_file():
        print(f"bench/ros2_live.py: {args.data} is not a data set (the TUM excerpt is at {TUM})",
              file=sys.stderr)
        return 1
    cv2.setNumThreads(1)
    if args.camera is not None:
        return camera_main(args.camera, args.data)
    load = os.getloadavg()
    if args.capacity < 1:
        print(f"--capacity must be >= 1, got {args.capacity}", file=sys.stderr)
        return 1
    r = edge_run(None if args.no_pin else 1, args.capacity, args.data, tracker_config(args.set))
    s = r["summary"]
    tracked = s["frames"] - s["lost_frames"]
    row = (f"| {r['published']} | {s['frames_received']} | {tracked} | {s['frames_dropped']} "
           f"({100 * s['frames_dropped'] / max(s['frames_received'], 1):.0f} %) | {s['frames_late']} | "
           f"{s.get('frames_source_dropped', '-')} | "
           f"{pct(r['track_ms'])} | {pct(r['track_cpu_ms'])} | {pct(r['pose_ms'])} | "
           f"{s['keyframes']} / {s['acked']} | "
           f"{pct(r['ack_ms'])} |")
    body = "\n".join([
        "## Live ROS 2 topics over Zenoh at 30 Hz (issue 38)",
        "",
        f"`python bench/ros2_live.py {' '.join(sys.argv[1:])}` at {git_rev()}; {machine()}; load average",
        f"{load[0]:.1f} / {load[1]:.1f} (1 / 5 min) when it started (a shared host: figures are upper",
        f"bounds). Two processes: a camera process (router on loopback, shared memory off; {args.data.name}",
        "as 640x480 rgb8 + 32FC1 depth, CDR on rmw_zenoh keys at 30 Hz, stamped with the host clock at each",
        "tick; a stand-in server that decodes and acks each keyframe, no store) and the edge daemon",
        f"(`--source ros2:`, stream slot of {args.capacity}, drop-oldest, labels `none`, outbox on disk), "
        f"{r['where']},",
        "numba/OpenCV threads = 1. Track ms: wall per frame, and the tracking thread's CPU time of it (the",
        "rest went to other threads and processes). Latency: camera stamp -> tracked pose, and -> keyframe",
        "acked, ms.",
        "",
        "| published | received | tracked | dropped | late | lost before the stream | track ms p50 / p95 "
        "| of it CPU "
        "| stamp -> pose ms p50 / p95 "
        "| keyframes / acked | stamp -> ack ms p50 / p95 |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
        row,
    ])
    publish(body, args.write, "ros2_live")
    return 0


if __name__ == "__main__":
    sys.exit(main())
