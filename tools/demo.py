"""``wardmap demo``: the whole system on loopback, for a newcomer's first command.

Starts ``wardmap router``, ``wardmap server`` and N ``wardmap edge`` processes as subprocesses
(the same Python: ``sys.executable -m wardmap.cli``); each edge renders its simulated robot live
(``--source sim:SCENARIO:SEED:ROBOT``) at the camera rate, so the robots run in parallel like
real ones. The demo waits for each child's ready line, shows progress while the edges run,
prints a summary table (keyframes produced vs delivered, ATE of the server's trajectory against
the simulator's ground truth, bytes per keyframe, publish -> ack latency) and keeps router +
server running until Ctrl-C (or stops at once with ``exit_after``).

Why this lives in ``tools/`` and not in ``server/`` or ``edge/``: the demo orchestrates processes
of both sides (edge agents, map server, router) and reads the simulator's and the data set's
outputs; ``wardmap.tools`` may import every runtime package, and nothing of the runtime imports
it. The thin entry point is :mod:`wardmap.cli.demo_cmd` (it parses the arguments, ``--http``
included, and calls :func:`run_demo`).

Every child runs in its own session (``start_new_session``) so that a Ctrl-C in the terminal
reaches only the demo, which then stops the children in order (edges, server, router):
SIGTERM, wait, SIGKILL as the last resort. Children are always stopped in a ``finally`` block.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import queue
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import IO, Any

from wardmap.shared.errors import WardmapError

log = logging.getLogger(__name__)

__all__ = ["DemoError", "DemoOptions", "RobotPlan", "RobotResult", "plan_robots", "run_demo"]

CAMERA_RATE_HZ = 10.0
"""The simulator's camera rate; frames = duration * this."""
MAX_ROBOTS = 4
READY_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 10.0
PROGRESS_PERIOD_S = 2.0
TAIL_LINES = 15
EXTRA_SCENARIOS = ("hospital_loop", "aisle_slow_2")
"""Scenarios for robots 2, 3, ... (alternating), with their own seeds."""


class DemoError(WardmapError):
    """The demo failed; the message is the one line shown to the user."""


@dataclass(frozen=True)
class DemoOptions:
    robots: int = 2
    duration_s: float = 30.0
    seed: int = 0
    exit_after: bool = False
    http_host: str = "127.0.0.1"
    """The map server's REST host (``--http``, parsed by the CLI)."""
    http_port: int = 8080
    """Its port; a free port on ``http_host`` is used when this one is busy."""
    keep: Path | None = None
    map_poses: bool = False
    """Start each robot at its ground-truth map pose (``--map-pose``); default: none, the
    server anchors robots by place recognition."""

    def __post_init__(self) -> None:
        if not 1 <= self.robots <= MAX_ROBOTS:
            raise DemoError(f"--robots must be 1..{MAX_ROBOTS}, got {self.robots}")
        if not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise DemoError(f"--duration must be a positive number of seconds, got {self.duration_s}")
        if self.frames < 3:
            raise DemoError(f"--duration {self.duration_s} gives fewer than 3 camera frames")

    @property
    def frames(self) -> int:
        return round(self.duration_s * CAMERA_RATE_HZ)


@dataclass(frozen=True)
class RobotPlan:
    """One robot of the demo: its id and where its data set comes from."""

    robot_id: str
    scenario: str
    seed: int
    sim_robot: str | None
    """The robot's name inside a multi-robot scenario (``two_robots``), else None."""

    @property
    def label(self) -> str:
        return f"{self.scenario}/{self.sim_robot}" if self.sim_robot else f"{self.scenario}"

    @property
    def source(self) -> str:
        """The edge's ``--source``: ``sim:SCENARIO:SEED[:ROBOT]``."""
        robot = f":{self.sim_robot}" if self.sim_robot else ""
        return f"sim:{self.scenario}:{self.seed}{robot}"


@dataclass
class RobotResult:
    robot_id: str
    dataset: str
    frames: int
    produced: int
    delivered: int
    ate_rmse_m: float | None
    ate_note: str
    bytes_per_keyframe: float | None
    latency_ms: dict[str, float] | None = None
    edge_summary: dict[str, Any] = field(default_factory=dict)


def plan_robots(n: int, seed: int) -> list[RobotPlan]:
    """Robots 0 and 1 from ``two_robots_meet`` (one world; they start apart and the second joins
    the first's path after about 15 s, where the server can anchor it); 2.. from other scenarios."""
    plans = []
    for i in range(n):
        if i < 2:
            plans.append(RobotPlan(f"robot_{i}", "two_robots_meet", seed, f"robot_{i}"))
        else:
            scenario = EXTRA_SCENARIOS[(i - 2) % len(EXTRA_SCENARIOS)]
            plans.append(RobotPlan(f"robot_{i}", scenario, seed + i, None))
    return plans


def _say(msg: str) -> None:
    """One progress line on stderr."""
    print(msg, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- child processes


def _child_env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("RUST_LOG", None)  # zenoh's Rust logging would flood the pipes
    return env


class Child:
    """A ``wardmap`` subprocess with its stdout lines in a queue and the tail of its stderr.

    Two daemon threads drain the pipes (so a chatty child never blocks on a full pipe) and
    copy everything to ``log_dir/NAME.log``.
    """

    def __init__(self, name: str, args: list[str], log_dir: Path) -> None:
        self.name = name
        self.cmd = [sys.executable, "-m", "wardmap.cli", *args]
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.stdout: list[str] = []
        self.tail: deque[str] = deque(maxlen=TAIL_LINES)
        self.summary_printed = False
        """Set on the first child (the router) once the demo printed its summary."""
        self._log = open(log_dir / f"{name}.log", "w", encoding="utf-8")  # noqa: SIM115 (closed in stop)
        self._log_lock = threading.Lock()
        self.proc = subprocess.Popen(
            self.cmd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=_child_env(),
            start_new_session=True,
        )
        assert self.proc.stdout is not None and self.proc.stderr is not None
        self._threads = [
            threading.Thread(target=self._drain, args=(self.proc.stdout, True), daemon=True),
            threading.Thread(target=self._drain, args=(self.proc.stderr, False), daemon=True),
        ]
        for t in self._threads:
            t.start()

    @property
    def pid(self) -> int:
        return self.proc.pid

    def _drain(self, stream: IO[str], is_stdout: bool) -> None:
        try:
            for line in stream:
                line = line.rstrip("\n")
                with self._log_lock:
                    if not self._log.closed:
                        self._log.write(("" if is_stdout else "[stderr] ") + line + "\n")
                        self._log.flush()
                if is_stdout:
                    self.stdout.append(line)
                    self.lines.put(line)
                else:
                    self.tail.append(line)
        except ValueError:  # the stream was closed under us during stop()
            pass
        finally:
            if is_stdout:
                self.lines.put(None)

    def stderr_tail(self) -> str:
        return "\n".join(f"  {self.name}: {line}" for line in self.tail) or f"  {self.name}: (no stderr)"

    def died(self, what: str) -> DemoError:
        """Print the stderr tail and build the one-line error for a child that died or hung."""
        for t in self._threads[1:]:
            t.join(timeout=2)  # let the stderr drain catch up with the exit
        _say(f"demo: last stderr lines of {self.name}:\n{self.stderr_tail()}")
        return DemoError(f"{self.name} {what} (log above; command: {' '.join(self.cmd[1:])})")

    def wait_line(self, accept: Callable[[str], bool], timeout_s: float) -> str:
        """The first stdout line ``accept`` takes; DemoError if the child exits or times out first."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise self.died(f"printed no ready line within {timeout_s:.0f} s")
            try:
                line = self.lines.get(timeout=min(left, 0.5))
            except queue.Empty:
                continue
            if line is None:
                try:
                    rc = self.proc.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    rc = None
                raise self.died(f"exited (code {rc}) before it was ready")
            if accept(line):
                return line

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """SIGTERM, wait, SIGKILL as the last resort; then close pipes and the log."""
        if self.proc.poll() is None:
            try:
                self.proc.terminate()
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                _say(f"demo: {self.name} ignored SIGTERM for {timeout_s:.0f} s; killing it")
                self.proc.kill()
                self.proc.wait(timeout=5)
        for t in self._threads:
            t.join(timeout=2)
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream is not None:
                with contextlib.suppress(OSError, ValueError):
                    stream.close()
        with self._log_lock:
            self._log.close()


# --------------------------------------------------------------------------- helpers


def _free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _port_free(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def choose_http(host: str, port: int) -> tuple[str, int, bool]:
    """``(host, port, moved)``: the ``--http`` address, or a free port on its host when it is busy."""
    if port != 0 and _port_free(host, port):
        return host, port, False
    try:
        return host, _free_port(host), port != 0
    except OSError as exc:
        raise DemoError(f"cannot listen on {host} for HTTP: {exc}") from exc


def _host_port(host: str, port: int) -> str:
    """``HOST:PORT`` as typed on the command line (``[IPv6]:PORT``)."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _url(host: str, port: int) -> str:
    return f"http://{_host_port(host, port)}"


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """Inside: SIGTERM raises KeyboardInterrupt (so the finally blocks stop the children)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _robot_counts(http: Any) -> dict[str, int]:
    r = http.get("/v1/robots")
    r.raise_for_status()
    return {row["robot_id"]: int(row["keyframes"]) for row in r.json()["robots"]}


def _payload_bytes(http: Any, robot_id: str) -> list[int]:
    sizes: list[int] = []
    cursor: str | None = None
    while True:
        params: dict[str, Any] = {"robot": robot_id, "limit": 1000}
        if cursor is not None:
            params["cursor"] = cursor
        r = http.get("/v1/keyframes", params=params)
        r.raise_for_status()
        body = r.json()
        sizes.extend(int(k["payload_bytes"]) for k in body["keyframes"])
        cursor = body["next_cursor"]
        if cursor is None:
            return sizes


def _mapping_backlog(http: Any) -> int | None:
    r = http.get("/metrics")
    r.raise_for_status()
    for line in r.text.splitlines():
        if line.startswith("wardmap_mapping_backlog "):
            return int(float(line.split()[1]))
    return None


@dataclass
class Anchoring:
    """How the server placed one robot's session on the map (``GET /v1/robots``).

    Attributes:
        robot_id: the robot.
        anchored: its session is on the map.
        after_s: seconds from its first keyframe to its anchoring (server clock).
        anchored_to: the session it was anchored through (its own: it set the map).
        T_map_odom: (4, 4) its odom frame on the map, as the server sent it.
        T_world_odom: (4, 4) the simulator's ground truth of that frame.
    """

    robot_id: str
    anchored: bool
    after_s: float | None
    anchored_to: str | None
    T_map_odom: Any
    T_world_odom: Any

    @property
    def sets_map(self) -> bool:
        """Its session set the map frame (the first session) or came with a map pose."""
        return self.anchored and (self.anchored_to or "").startswith(f"{self.robot_id}/")


def robot_anchoring(plans: list[RobotPlan], http: Any, timeout_s: float = 60.0) -> list[Anchoring]:
    """Each robot's anchoring once the server's back-end and mapping caught up."""
    import numpy as np

    from wardmap.shared.se3 import transform_from_tum
    from wardmap.sim.live import LiveRun

    deadline = time.monotonic() + timeout_s
    while (backlog := _mapping_backlog(http)) not in (0, None) and time.monotonic() < deadline:
        _say(f"demo: mapping stage backlog {backlog} keyframes")
        time.sleep(1.0)
    r = http.get("/v1/robots")
    r.raise_for_status()
    by_id = {row["robot_id"]: row for row in r.json()["robots"]}
    out = []
    for p in plans:
        row = by_id.get(p.robot_id, {})
        T = row.get("T_map_odom")
        T_map_odom = None if T is None else transform_from_tum([*T["t"], *T["q_xyzw"]])
        at = row.get("anchored_at_s")
        after = None if at is None or "first_seen_s" not in row else max(0.0, at - row["first_seen_s"])
        gt = np.asarray(LiveRun(p.scenario, p.seed, p.sim_robot, frames=1).T_world_odom(), np.float64)
        out.append(Anchoring(p.robot_id, bool(row.get("anchored")), after, row.get("anchored_to"), T_map_odom,
                             gt))
    return out


def map_from_world(anchoring: list[Anchoring]) -> Any:
    """``T_map_world`` (4, 4): the simulated world on the server's map, from the robot whose
    session set the map (anchored through itself); identity when none did."""
    import numpy as np

    for a in anchoring:
        if a.sets_map and a.T_map_odom is not None:
            return a.T_map_odom @ np.linalg.inv(a.T_world_odom)
    return np.eye(4)


def alignment_error(a: Anchoring, T_map_world: Any) -> tuple[float, float] | None:
    """Translation (m) and rotation (deg) between the robot's ``T_map_odom`` and the ground
    truth's ``T_map_world @ T_world_odom``; None when it is not anchored."""
    import numpy as np

    if not a.anchored or a.T_map_odom is None:
        return None
    D = np.linalg.inv(a.T_map_odom) @ T_map_world @ a.T_world_odom
    angle = math.degrees(math.acos(float(np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))
    return float(np.linalg.norm(D[:3, 3])), angle


def format_anchoring(anchoring: list[Anchoring]) -> str:
    """One line per robot: whether and when the server anchored it, and the alignment error."""
    T_map_world = map_from_world(anchoring)
    lines = []
    for a in anchoring:
        if not a.anchored:
            lines.append(f"ANCHOR {a.robot_id}: not anchored (its path has not met a mapped place yet); "
                         "its objects wait")
            continue
        err = alignment_error(a, T_map_world)
        through = (a.anchored_to or "?").split("/", 1)[0]
        how = "sets the map" if a.sets_map else f"anchored through {through}'s map"
        when = "" if a.after_s is None else f" {a.after_s:.1f} s after its first keyframe"
        if err is None:
            lines.append(f"ANCHOR {a.robot_id}: {how}{when}")
        else:
            lines.append(f"ANCHOR {a.robot_id}: {how}{when}; alignment error {100 * err[0]:.1f} cm, "
                         f"{err[1]:.2f} deg against ground truth")
    return "\n".join(lines)


def map_summary(plans: list[RobotPlan], http: Any, timeout_s: float = 120.0,
                T_map_world: Any = None) -> str:
    """Wait for the server's mapping stage to catch up, then the objects on the map, each checked
    against the simulated objects of its category (moved onto the map with ``T_map_world``,
    (4, 4), identity when None), and the doors it found against the simulated world's doors
    (``GET /v1/objects?category=door``)."""
    import numpy as np

    T_mw = np.eye(4) if T_map_world is None else np.asarray(T_map_world, np.float64)

    from wardmap.sim.live import LiveRun

    deadline = time.monotonic() + timeout_s
    while (backlog := _mapping_backlog(http)) not in (0, None) and time.monotonic() < deadline:
        _say(f"demo: mapping stage backlog {backlog} keyframes")
        time.sleep(1.0)
    r = http.get("/v1/categories")
    r.raise_for_status()
    counts = {c["name"]: c["count"] for c in r.json()["categories"] if c["count"]}
    lines = ["MAP: objects by category: " + (", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
                                            or "none yet")]
    r = http.get("/v1/objects", params={"category": "door", "limit": 100})
    r.raise_for_status()
    doors = [o["position"] for o in r.json()["objects"]]
    # Robots of one scenario and seed share its world: each object once.
    worlds = {(p.scenario, p.seed): p for p in plans}.values()
    simulated = [(o["class"], (T_mw @ np.asarray(o["T_world_object"]))[:3, 3]) for p in worlds
                 for o in LiveRun(p.scenario, p.seed, p.sim_robot, frames=1).objects()["objects"]]
    lines.extend(_map_check(http, simulated))
    lines.append(f"GET /v1/objects?category=door: {len(doors)} doors on the map; the simulated worlds have "
                 f"{sum(cls == 'door' for cls, _ in simulated)} (a robot maps only the doors it passes)")
    shown = 8
    for pos in doors[:shown]:
        lines.append(f"  door at ({pos[0]:.2f}, {pos[1]:.2f}, {pos[2]:.2f}) m: "
                     f"nearest simulated door {_nearest(pos, 'door', simulated):.2f} m")
    if len(doors) > shown:
        lines.append(f"  ... and {len(doors) - shown} more")
    return "\n".join(lines)


def _nearest(position: Any, category: str, simulated: list[tuple[str, Any]]) -> float:
    """Horizontal distance (metres) from ``position`` (3,) to the nearest simulated object of
    ``category`` (``simulated``: (class, (3,) position) pairs); inf when there is none."""
    import numpy as np

    xy = np.asarray(position, float)[:2]
    return min((float(np.linalg.norm(xy - xyz[:2])) for cls, xyz in simulated if cls == category),
               default=float("inf"))


def _map_check(http: Any, simulated: list[tuple[str, Any]], within_m: float = 0.5) -> list[str]:
    """Every object on the map against the simulated objects of its class (their start
    positions; movable ones may have been moved since): how many lie within ``within_m``
    (horizontal distance, metres), and the others, so a wrong object is seen, not hidden."""
    objects: list[dict[str, Any]] = []
    offset: int | None = 0
    while offset is not None:
        r = http.get("/v1/objects", params={"limit": 500, "offset": offset})
        r.raise_for_status()
        body = r.json()
        objects += body["objects"]
        offset = body["next_offset"]
    far = [(o, d) for o in objects if (d := _nearest(o["position"], o["category"], simulated)) > within_m]
    lines = [f"CHECK: {len(objects) - len(far)} of {len(objects)} objects on the map lie within {within_m} m "
             f"of a simulated object of their category"]
    for o, d in far:
        x, y, z = o["position"]
        cat = o["category"]
        what = f"nearest simulated {cat} {d:.2f} m" if math.isfinite(d) else f"no simulated {cat}"
        lines.append(f"  not: {cat} {o['object_id']} at ({x:.2f}, {y:.2f}, {z:.2f}) m, {what}")
    return lines


def map_pose(plan: RobotPlan) -> str:
    """``X,Y,YAW_DEG`` of the robot's start on the map: the simulated world is the map, and the
    robot starts at a known pose (as a real one starts at its dock)."""
    import numpy as np

    from wardmap.sim.live import LiveRun

    T = LiveRun(plan.scenario, plan.seed, plan.sim_robot, frames=1).T_world_odom()
    yaw = float(np.degrees(np.arctan2(T[1, 0], T[0, 0])))
    return f"{T[0, 3]:.4f},{T[1, 3]:.4f},{yaw:.3f}"


def _ate(http: Any, robot_id: str, plan: RobotPlan) -> tuple[float | None, str]:
    """RMSE ATE (SE3-aligned) of the server's trajectory against the simulator's ground truth."""
    import numpy as np

    from wardmap.shared.metrics import ate
    from wardmap.shared.se3 import transform_from_tum

    r = http.get(f"/v1/robots/{robot_id}/trajectory", params={"format": "json"})
    if r.status_code == 404:
        return None, "no trajectory on the server"
    r.raise_for_status()
    poses = r.json()["poses"]
    from wardmap.sim.live import LiveRun

    gt = LiveRun(plan.scenario, plan.seed, plan.sim_robot).groundtruth()
    stamps = np.array([p["stamp"] for p in poses], np.float64)
    rows = [transform_from_tum([*p["t"], *p["q_xyzw"]]) for p in poses]
    T = np.stack(rows) if rows else np.zeros((0, 4, 4))
    try:
        # the server's poses are T_odom_camera of the robot's session; SE3 alignment maps odom to world
        res = ate(stamps, T, gt[0], gt[1], align="se3")
    except WardmapError as exc:
        return None, str(exc)
    return res.rmse, f"{res.n} poses"


# --------------------------------------------------------------------------- summary


def format_summary(results: list[RobotResult], opts: DemoOptions) -> str:
    head = ("robot", "source", "frames", "produced", "delivered", "ATE rmse [m]", "bytes/keyframe",
            "latency p50/p99 [ms]")
    rows = [head]
    for r in results:
        rows.append((
            r.robot_id,
            r.dataset,
            str(r.frames),
            str(r.produced),
            str(r.delivered),
            f"{r.ate_rmse_m:.4f}" if r.ate_rmse_m is not None else "n/a",
            f"{r.bytes_per_keyframe:,.0f}" if r.bytes_per_keyframe is not None else "n/a",
            f"{r.latency_ms['p50']:.0f}/{r.latency_ms['p99']:.0f}" if r.latency_ms else "n/a",
        ))
    widths = [max(len(row[i]) for row in rows) for i in range(len(head))]
    lines = [f"SUMMARY: {len(results)} robots, {opts.duration_s:g} s of camera at {CAMERA_RATE_HZ:g} Hz, "
             f"seed {opts.seed}"]
    for k, row in enumerate(rows):
        lines.append("  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths,
                                                                                                  strict=True))))
        if k == 0:
            lines.append("  ".join("-" * w for w in widths))
    for r in results:
        if r.ate_rmse_m is None:
            lines.append(f"{r.robot_id}: no ATE: {r.ate_note}")
    lines.append("produced: keyframes the edge made (its summary); delivered: keyframes the server stored; "
                 "ATE: server trajectory vs ground truth, SE3-aligned")
    lines.append("latency: from the edge's first publish of a keyframe to its ack (the server acks "
                 "after the database commit)")
    return "\n".join(lines)


# --------------------------------------------------------------------------- the demo


def run_demo(opts: DemoOptions, *, wait: Callable[[], None] | None = None) -> int:
    """Run the demo; 0 on success. Raises DemoError (one line) on failure.

    Args:
        wait: called after the summary instead of waiting for Ctrl-C (tests); ignored with
            ``opts.exit_after``.
    """
    if opts.keep is not None:
        work = opts.keep.resolve()
        if work.exists() and any(work.iterdir()):
            raise DemoError(f"--keep {work}: folder exists and is not empty")
        work.mkdir(parents=True, exist_ok=True)
    else:
        work = Path(tempfile.mkdtemp(prefix="wardmap-demo-"))
    note = "kept" if opts.keep is not None else "deleted on exit; --keep DIR keeps it"
    _say(f"demo: work folder {work} ({note})")
    children: list[Child] = []
    try:
        with _sigterm_as_interrupt():
            try:
                return _run(opts, work, children, wait)
            except KeyboardInterrupt:
                if not _summary_printed(children):
                    raise  # interrupted before the summary: main() reports it (exit 130)
                _say("demo: stopping")
                return 0
    finally:
        for child in reversed(children):  # edges first, then server, then router
            child.stop()
        if opts.keep is None:
            shutil.rmtree(work, ignore_errors=True)


def _summary_printed(children: list[Child]) -> bool:
    return bool(children) and children[0].summary_printed


def _read_token(db_url: str) -> str:
    """A new ``read`` token in the store at ``db_url`` (created now), for a demo off loopback."""
    from wardmap.server.store import open_store
    from wardmap.server.tokens import create_token

    with open_store(db_url) as store:
        return create_token(store, "read", "wardmap demo").text


def _run(opts: DemoOptions, work: Path, children: list[Child], wait: Callable[[], None] | None) -> int:
    import httpx

    from wardmap.server.app import is_loopback

    plans = plan_robots(opts.robots, opts.seed)
    host, port, moved = choose_http(opts.http_host, opts.http_port)
    if moved:
        _say(f"demo: HTTP address {_host_port(opts.http_host, opts.http_port)} is busy; "
             f"using {host}:{port} instead")
    logs = work / "logs"
    logs.mkdir()

    def start(name: str, args: list[str], accept: Callable[[str], bool]) -> Child:
        child = Child(name, args, logs)
        children.append(child)
        line = child.wait_line(accept, READY_TIMEOUT_S)
        _say(f"demo: {name} (pid {child.pid}): {line}")
        return child

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    router = start("router", ["router", "--listen", endpoint], lambda s: s.startswith("router listening on"))
    url = _url(host, port)
    db_url = f"sqlite:///{work / 'map.db'}"
    # On loopback the API runs without tokens; elsewhere the demo makes a read token and prints it.
    token = None if is_loopback(host) else _read_token(db_url)
    server = start(
        "server",
        ["server", "--connect", endpoint, "--db", db_url, "--http", f"{host}:{port}",
         *(["--insecure-loopback"] if token is None else [])],
        lambda s: s.startswith("server ready:"),
    )
    headers = {} if token is None else {"Authorization": f"Bearer {token}"}
    edges: dict[str, Child] = {}
    for p in plans:
        args = ["edge", "--robot", p.robot_id, "--source", p.source, "--connect", endpoint,
                "--outbox", str(work / "outbox" / p.robot_id), "--rate", f"{CAMERA_RATE_HZ:g}",
                "--max-frames", str(opts.frames), "--labels", "oracle"]  # finds people to blank
        if opts.map_poses:
            args += ["--map-pose", map_pose(p)]
        edges[p.robot_id] = start(f"edge {p.robot_id}", args, lambda s: " ready: session " in s)

    with httpx.Client(base_url=url, timeout=10.0, headers=headers) as http:
        _watch(opts, router, server, edges, http)
        results = _collect(plans, edges, http)
        print(format_summary(results, opts), flush=True)
        router.summary_printed = True
        short = [r.robot_id for r in results if r.delivered != r.produced or r.produced == 0]
        if short:
            raise DemoError(f"keyframes not all delivered (or none produced) for {', '.join(short)}")
        anchoring = robot_anchoring(plans, http)
        print(format_anchoring(anchoring), flush=True)
        print(map_summary(plans, http, T_map_world=map_from_world(anchoring)), flush=True)
        page = url + "/" if token is None else f"{url}/#token={token}"
        print(f"map server: {url}  (open {page} in a browser for the map; try "
              f"{url}/v1/objects?category=door, {url}/v1/categories, {url}/v1/robots, {url}/metrics)",
              flush=True)
        if token is None:
            print("REST API: insecure-loopback (no token needed; only this host can reach it)", flush=True)
        else:
            print(f"REST API read token: {token}  (send it as 'Authorization: Bearer TOKEN')", flush=True)
        if opts.exit_after:
            return 0
        if wait is not None:
            wait()
            return 0
        _say("demo: router and map server keep running; press Ctrl-C to stop them")
        while True:  # until Ctrl-C / SIGTERM (KeyboardInterrupt, handled in run_demo)
            for child in (router, server):
                if child.proc.poll() is not None:
                    raise child.died(f"exited (code {child.proc.returncode}) while serving")
            time.sleep(0.5)


def _watch(opts: DemoOptions, router: Child, server: Child, edges: dict[str, Child], http: Any) -> None:
    """Every ~2 s one progress line (keyframes on the server per robot) until every edge exited."""
    started = time.monotonic()
    deadline = started + 120.0 + 5.0 * opts.duration_s  # generous: the tracker may be slower than 10 Hz
    next_report = started + PROGRESS_PERIOD_S
    while any(e.proc.poll() is None for e in edges.values()):
        for child in (router, server):
            if child.proc.poll() is not None:
                raise child.died(f"exited (code {child.proc.returncode}) while the edges were running")
        now = time.monotonic()
        if now > deadline:
            running = [name for name, e in edges.items() if e.proc.poll() is None]
            raise edges[running[0]].died(f"still running after {now - started:.0f} s")
        if now >= next_report:
            next_report = now + PROGRESS_PERIOD_S
            try:
                counts = _robot_counts(http)
                state = ", ".join(
                    f"{rid} {counts.get(rid, 0)}{'' if e.proc.poll() is None else ' (done)'}"
                    for rid, e in edges.items()
                )
            except httpx_errors() as exc:
                state = f"server not answering ({exc})"
            _say(f"demo: {now - started:5.1f} s: keyframes on the server: {state}")
        time.sleep(0.1)


def httpx_errors() -> tuple[type[Exception], ...]:
    import httpx

    return (httpx.HTTPError,)


def _collect(plans: list[RobotPlan], edges: dict[str, Child], http: Any) -> list[RobotResult]:
    counts = _robot_counts(http)
    results = []
    for p in plans:
        edge = edges[p.robot_id]
        rc = edge.proc.wait()
        for t in edge._threads:
            t.join(timeout=5)
        if rc != 0:
            raise edge.died(f"exited with code {rc}")
        summary: dict[str, Any] | None = None
        for line in reversed(edge.stdout):
            with contextlib.suppress(ValueError):
                value = json.loads(line)
                if isinstance(value, dict):
                    summary = value
                    break
        if summary is None:
            raise edge.died("printed no JSON summary")
        sizes = _payload_bytes(http, p.robot_id)
        rmse, note = _ate(http, p.robot_id, p)
        results.append(RobotResult(
            robot_id=p.robot_id,
            dataset=p.label if p.sim_robot else f"{p.label} seed {p.seed}",
            frames=int(summary.get("frames", 0)),
            produced=int(summary.get("keyframes", 0)),
            delivered=counts.get(p.robot_id, 0),
            ate_rmse_m=rmse,
            ate_note=note,
            bytes_per_keyframe=sum(sizes) / len(sizes) if sizes else None,
            latency_ms=summary.get("latency_ms"),
            edge_summary=summary,
        ))
    return results
