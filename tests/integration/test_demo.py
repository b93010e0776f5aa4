"""``wardmap demo --exit`` end to end: simulation, router, server and two edge agents as real
subprocesses; the summary on stdout and no child process left behind afterwards."""

from __future__ import annotations

import math
import os
import re
import subprocess
from pathlib import Path

import pytest
from procs import child_env, wardmap_cmd
from procs import free_port as _free_port

pytest.importorskip("zenoh")

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]

RUN_TIMEOUT_S = 150.0
DURATION_S = 30
"""Long enough for robot_1 to join robot_0's path (after about 15 s) and be anchored."""
ROW = re.compile(r"^(robot_\d+)\s+\S+\s+(\d+)\s+(\d+)\s+(\d+)\s+(\S+)\s+([\d,]+)\s+(\d+)/(\d+)$")


def _cmdline(pid: int) -> str | None:
    """The command line of ``pid``, or None when no such process exists."""
    try:
        raw = (Path("/proc") / str(pid) / "cmdline").read_bytes()
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        return None
    return raw.replace(b"\0", b" ").decode(errors="replace")


def _processes_mentioning(text: str) -> list[str]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) != os.getpid():
            cmd = _cmdline(int(entry.name))
            if cmd is not None and text in cmd:
                found.append(f"{entry.name}: {cmd}")
    return found


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to look for left-over processes")
def test_demo_two_robots_exits_cleanly() -> None:
    """Two simulated robots for 30 s, started without map poses, through a real router, server
    and two edges: the demo exits 0, every keyframe produced is delivered, robot_0 sets the map
    and the server anchors robot_1 by place recognition (alignment within 5 cm and 1 deg of
    ground truth), the map's doors and positions match the simulated world, and no child process
    or work folder is left behind."""
    http = f"127.0.0.1:{_free_port()}"
    cmd = wardmap_cmd("demo", "--robots", "2", "--duration", str(DURATION_S), "--exit", "--http", http)
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=RUN_TIMEOUT_S, env=child_env())
    assert done.returncode == 0, done.stderr[-4000:]
    assert "Traceback" not in done.stderr

    assert "SUMMARY" in done.stdout
    rows = {m.group(1): m for line in done.stdout.splitlines() if (m := ROW.match(line.strip()))}
    assert set(rows) == {"robot_0", "robot_1"}, done.stdout
    for robot, m in rows.items():
        frames, produced, delivered = int(m.group(2)), int(m.group(3)), int(m.group(4))
        assert frames == 10 * DURATION_S, (robot, done.stdout)
        assert delivered == produced > 0, (robot, done.stdout)
        ate = float(m.group(5))  # "n/a" would raise here
        assert math.isfinite(ate) and ate >= 0.0, (robot, done.stdout)
        assert 0 < int(m.group(6).replace(",", "")) <= 100_000, (robot, done.stdout)  # bytes/keyframe
        assert 0 < int(m.group(7)) <= int(m.group(8)), (robot, done.stdout)  # latency p50 <= p99, ms
    assert re.search(r"^ANCHOR robot_0: sets the map", done.stdout, re.M), done.stdout
    anchor = re.search(r"^ANCHOR robot_1: anchored through robot_0's map ([\d.]+) s after its first "
                       r"keyframe; alignment error ([\d.]+) cm, ([\d.]+) deg", done.stdout, re.M)
    assert anchor, done.stdout
    assert float(anchor[2]) <= 5.0 and float(anchor[3]) <= 1.0, done.stdout
    assert "map server: http://127.0.0.1:" in done.stdout
    assert "REST API: insecure-loopback" in done.stdout  # the demo says how its API is open
    # the map server's mapping stage ran: the demo asked it for the doors
    assert re.search(r"^MAP: objects by category: ", done.stdout, re.MULTILINE), done.stdout
    doors = re.search(r"^GET /v1/objects\?category=door: \d+ doors on the map; the simulated worlds have "
                      r"(\d+)", done.stdout, re.MULTILINE)
    assert doors, done.stdout
    from wardmap.sim.live import LiveRun  # both robots drive the one two_robots_meet world (seed 0)

    world = LiveRun("two_robots_meet", 0, "robot_0", frames=1).objects()["objects"]
    assert int(doors[1]) == sum(o["class"] == "door" for o in world), done.stdout
    check = re.search(r"^CHECK: (\d+) of (\d+) objects on the map lie within 0.5 m", done.stdout, re.M)
    assert check, done.stdout
    near, total = int(check[1]), int(check[2])
    assert total > 0 and near >= 0.8 * total, done.stdout
    assert len(re.findall(r"^  not: ", done.stdout, re.MULTILINE)) == total - near

    # every child the demo started is gone, and its temporary work folder with it
    pids = [int(p) for p in re.findall(r"^demo: .*\(pid (\d+)\):", done.stderr, re.MULTILINE)]
    assert len(pids) == 4, done.stderr  # router, server, two edges
    for pid in pids:
        cmd_left = _cmdline(pid)
        assert cmd_left is None or "wardmap" not in cmd_left, f"child {pid} still runs: {cmd_left}"
    work = re.search(r"^demo: work folder (\S+) ", done.stderr, re.MULTILINE)
    assert work is not None, done.stderr
    assert _processes_mentioning(work.group(1)) == []
    assert not Path(work.group(1)).exists()
