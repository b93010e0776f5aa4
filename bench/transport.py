"""Transport benchmark (issue 4): bytes per keyframe, latency, ingest throughput, 4 robots in real time.

Real processes on loopback, as deployed: a ``wardmap router``, a ``wardmap server`` (SQLite,
``synchronous=FULL``) and four ``wardmap edge`` agents (each tracking a simulated data set at
the camera rate, 10 Hz). Zenoh shared memory is off everywhere (the processes stand for
machines on a network), multicast scouting off.

1. **Real time**: the four agents run their sequences at 10 Hz. The bench subscribes to
   their heartbeats (1 Hz) and records each robot's outbox backlog (keyframes made and not
   yet acked by the server). The server keeps up when the backlog does not grow: the
   table gives the backlog's maximum and the least-squares slope of the total backlog over
   time (keyframes per second; ~0 when keeping up). Bytes per keyframe are the server's
   stored payload sizes; latency is each agent's publish -> ack time (the server acks
   after its database commit, so this bounds publish -> commit from above).
2. **Throughput**: a fresh server; the bench re-publishes every payload of phase 1 as fast
   as Zenoh accepts them (reliable, congestion control block) and times until the last ack:
   keyframes and megabytes per second the server ingests, decodes, validates and commits.

With ``--security mtls`` the same run goes through a router on ``tls/`` with mutual TLS and the
fleet ACL (docs/security.md): ``wardmap certs`` makes a site CA and a certificate for the
router, the server, each robot and the bench's own sessions (a server certificate: they
subscribe to every robot's heartbeats and re-publish keyframes as every robot), and the
table is written as its own section.

Data sets are cached under ``--data`` (``<scenario>_s<seed>``, shared with bench/tracking.py).

    python bench/transport.py [--frames 300] [--data out/bench_data] [--security none|mtls]
                              [--write BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import git_rev, machine, write_section

from wardmap.server.certs import ACL_FILE, init_ca, issue
from wardmap.shared.dataset import DatasetReader
from wardmap.shared.wire import decode_ack, decode_heartbeat
from wardmap.shared.zenoh_config import ZenohOptions, ack_key, client_config, heartbeat_key, keyframe_key
from wardmap.shared.zenoh_load import load_zenoh_config
from wardmap.sim.runner import generate

ROOT = Path(__file__).resolve().parents[1]
ROBOTS = (  # (robot id, scenario, sim robot folder or None): the demo's four robots, seed 0
    ("robot_0", "two_robots", "robot_0"),
    ("robot_1", "two_robots", "robot_1"),
    ("robot_2", "hospital_loop", None),
    ("robot_3", "aisle_slow_2", None),
)
READY_TIMEOUT_S = 60.0
GOAL_BYTES = 100_000


# ------------------------------------------------------------------------------ processes


class Proc:
    """A ``wardmap`` subprocess; stdout lines go to a queue, stderr to a log file."""

    def __init__(self, args: list[str], log: Path) -> None:
        env = dict(os.environ)
        env.pop("RUST_LOG", None)
        self._log = log.open("w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "wardmap.cli", *args], stdout=subprocess.PIPE, stderr=self._log,
            text=True, env=env,
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._pump, args=(self.proc.stdout,), daemon=True).start()

    def _pump(self, stream: IO[str] | None) -> None:
        assert stream is not None
        for line in stream:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def wait_line(self, accept: Callable[[str], bool], timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = self.lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise SystemExit(f"{self.proc.args}: no ready line in {timeout:.0f} s") from None
            if line is None:
                raise SystemExit(f"{self.proc.args}: exited (code {self.proc.wait()}); see {self._log.name}")
            if accept(line):
                return line

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Site:
    """Who connects how: plain tcp (``site`` None) or mutual TLS with certificates in ``site``."""

    def __init__(self, site: Path | None) -> None:
        self.site = site

    @classmethod
    def make(cls, security: str, work: Path, robots: list[str]) -> Site:
        """``none``: plain tcp; ``mtls``: a CA and certificates for every process in ``work/site``."""
        if security == "none":
            return cls(None)
        site = work / "site"
        init_ca(site)
        issue(site, "router", "router", hosts=["127.0.0.1"])
        for name in ("server", "bench"):
            issue(site, name, "server")
        for robot_id in robots:
            issue(site, robot_id, "robot")
        return cls(site)

    @property
    def scheme(self) -> str:
        return "tcp" if self.site is None else "tls"

    def options(self, name: str) -> ZenohOptions:
        if self.site is None:
            return ZenohOptions()
        return ZenohOptions(tls_ca=str(self.site / "ca.crt"), tls_cert=str(self.site / f"{name}.crt"),
                            tls_key=str(self.site / f"{name}.key"))

    def flags(self, name: str) -> list[str]:
        """The ``wardmap`` flags of process ``name`` (its certificate; the router also its ACL)."""
        if self.site is None:
            return []
        o = self.options(name)
        acl = ["--zenoh-config", str(self.site / ACL_FILE)] if name == "router" else []
        return ["--tls-ca", o.tls_ca, "--tls-cert", o.tls_cert, "--tls-key", o.tls_key, *acl]


def start_router(work: Path, site: Site) -> tuple[Proc, str]:
    endpoint = f"{site.scheme}/127.0.0.1:{_free_port()}"
    router = Proc(["router", "--listen", endpoint, *site.flags("router")], work / "router.log")
    router.wait_line(lambda s: s.startswith("router listening"), READY_TIMEOUT_S)
    return router, endpoint


def start_server(endpoint: str, db: Path, work: Path, name: str, site: Site) -> tuple[Proc, str]:
    port = _free_port()
    server = Proc(["server", "--connect", endpoint, "--db", f"sqlite:///{db}", "--http", f"127.0.0.1:{port}",
                   *site.flags("server")], work / f"{name}.log")
    server.wait_line(lambda s: s.startswith("server ready:"), READY_TIMEOUT_S)
    return server, f"http://127.0.0.1:{port}"


def zenoh_client(endpoint: str, site: Site) -> Any:
    import zenoh

    options = site.options("bench")
    return zenoh.open(load_zenoh_config(client_config([endpoint], options=options), options))


# ------------------------------------------------------------------------------ phases


def datasets(data: Path, frames: int) -> dict[str, Path]:
    out = {}
    for robot_id, scenario, sim_robot in ROBOTS:
        folder = data / f"{scenario}_s0"
        if not (folder / ("robot_0" if sim_robot else "") / "rgb.txt").is_file():
            print(f"generating {scenario} seed 0 into {folder} ...", file=sys.stderr, flush=True)
            generate(scenario, 0, folder, overwrite=True)
        path = folder / sim_robot if sim_robot else folder
        if len(DatasetReader(path)) < frames:
            raise SystemExit(f"{path} has fewer than {frames} frames; lower --frames")
        out[robot_id] = path
    return out


def real_time(endpoint: str, sets: dict[str, Path], frames: int, work: Path, site: Site) -> dict[str, Any]:
    """Phase 1: four agents at 10 Hz; heartbeats sampled for the backlog."""
    backlog: dict[str, list[tuple[float, int]]] = {r: [] for r in sets}
    lock = threading.Lock()
    t0 = time.monotonic()

    def on_heartbeat(sample: Any) -> None:
        hb = decode_heartbeat(sample.payload.to_bytes())
        with lock:
            backlog[hb.robot_id].append((time.monotonic() - t0, int(hb.stats["pending"])))

    edges: dict[str, Proc] = {}
    with zenoh_client(endpoint, site) as session:
        subs = [session.declare_subscriber(heartbeat_key(r), on_heartbeat) for r in sets]
        try:
            for robot_id, path in sets.items():
                edges[robot_id] = Proc(
                    ["edge", "--robot", robot_id, "--source", str(path), "--connect", endpoint,
                     "--outbox", str(work / "outbox" / robot_id), "--rate", "10",
                     "--max-frames", str(frames), "--privacy", "off", *site.flags(robot_id)],
                    work / f"edge_{robot_id}.log",
                )
            summaries = {}
            for edge in edges.values():
                edge.wait_line(lambda s: " ready: session " in s, READY_TIMEOUT_S)
            for robot_id, edge in edges.items():
                line = edge.wait_line(lambda s: s.startswith("{"), 60.0 + frames)
                summaries[robot_id] = json.loads(line)
                edge.proc.wait(30)
        finally:
            for sub in subs:
                sub.undeclare()
            for edge in edges.values():
                edge.stop()
    wall = time.monotonic() - t0
    # Total backlog over time: per-robot samples interpolated on a 1 s grid.
    grid = np.arange(0.0, wall, 1.0)
    total = np.zeros_like(grid)
    for samples in backlog.values():
        if samples:
            t, p = np.array(samples, float).T
            total += np.interp(grid, t, p, left=0.0, right=p[-1])
    slope = float(np.polyfit(grid, total, 1)[0]) if len(grid) >= 3 else float("nan")
    return {"summaries": summaries, "wall_s": wall, "max_backlog": int(total.max(initial=0)),
            "slope": slope, "heartbeats": sum(len(v) for v in backlog.values())}


def throughput(endpoint: str, payloads: list[tuple[str, bytes]], site: Site) -> dict[str, float]:
    """Phase 2: publish every payload as fast as possible; time until the last ack."""
    import zenoh

    robots = sorted({r for r, _ in payloads})
    acked = threading.Semaphore(0)
    statuses: dict[str, int] = {}

    def on_ack(sample: Any) -> None:
        ack = decode_ack(sample.payload.to_bytes())
        statuses[ack.status] = statuses.get(ack.status, 0) + 1
        acked.release()

    with zenoh_client(endpoint, site) as session:
        subs = [session.declare_subscriber(ack_key(r), on_ack) for r in robots]
        pubs = {
            r: session.declare_publisher(keyframe_key(r), reliability=zenoh.Reliability.RELIABLE,
                                         congestion_control=zenoh.CongestionControl.BLOCK)
            for r in robots
        }
        time.sleep(1.0)  # let the subscriptions propagate through the router
        t0 = time.perf_counter()
        for robot_id, payload in payloads:
            pubs[robot_id].put(payload)
        t_pub = time.perf_counter() - t0
        for _ in payloads:
            if not acked.acquire(timeout=120):
                raise SystemExit("throughput: acks stopped arriving")
        elapsed = time.perf_counter() - t0
        for p in pubs.values():
            p.undeclare()
        for s in subs:
            s.undeclare()
    mb = sum(len(p) for _, p in payloads) / 1e6
    return {"n": len(payloads), "seconds": elapsed, "publish_s": t_pub, "kf_per_s": len(payloads) / elapsed,
            "mb_per_s": mb / elapsed, "stored": statuses.get("stored", 0)}


def stored_payloads(db: Path) -> list[tuple[str, bytes]]:
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as conn:
        rows = conn.execute("SELECT robot_id, payload FROM keyframes ORDER BY received_s").fetchall()
    return [(str(r), bytes(p)) for r, p in rows]


# ------------------------------------------------------------------------------ main


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="frames per robot (10 Hz: 300 = 30 s)")
    ap.add_argument("--data", type=Path, default=ROOT / "out" / "bench_data")
    ap.add_argument("--security", choices=("none", "mtls"), default="none",
                    help="mtls: router on tls/ with mutual TLS and the fleet ACL (docs/security.md)")
    ap.add_argument("--write", type=Path, help="write the table into this markdown file")
    args = ap.parse_args()
    sets = datasets(args.data, args.frames)
    with tempfile.TemporaryDirectory(prefix="wardmap-bench-transport-") as tmp:
        work = Path(tmp)
        site = Site.make(args.security, work, list(sets))
        router, endpoint = start_router(work, site)
        try:
            db = work / "rt.db"
            server, _ = start_server(endpoint, db, work, "server_rt", site)
            try:
                rt = real_time(endpoint, sets, args.frames, work, site)
            finally:
                server.stop()
            payloads = stored_payloads(db)
            server2, _ = start_server(endpoint, work / "flood.db", work, "server_flood", site)
            try:
                tp = throughput(endpoint, payloads, site)
            finally:
                server2.stop()
        finally:
            router.stop()
    body = report(rt, tp, payloads, args)
    print(body)
    if args.write:
        write_section(args.write, "transport" if args.security == "none" else "transport_mtls", body)


def report(rt: dict[str, Any], tp: dict[str, float], payloads: list[tuple[str, bytes]],
           args: argparse.Namespace) -> str:
    sizes: dict[str, list[int]] = {}
    for robot_id, p in payloads:
        sizes.setdefault(robot_id, []).append(len(p))
    mtls = args.security == "mtls"
    lines = [
        "## Transport over mutual TLS with the fleet ACL (issue 39)" if mtls
        else "## Transport: 4 robots, router, server (issue 4)",
        "",
        f"Command: `python bench/transport.py --frames {args.frames}{' --security mtls' if mtls else ''}`. "
        f"Machine: {machine()}; commit {git_rev()}.",
        "Real processes on loopback, Zenoh shared memory off; each agent tracks its simulated sequence at "
        "10 Hz (the demo's four robots, seed 0)."
        + (" Router on tls/ with mutual TLS and the ACL of `wardmap certs`; every process has its own "
           "certificate." if mtls else ""),
        "",
        "| robot | frames | keyframes | delivered | bytes/keyframe mean | max "
        "| latency p50 ms | p95 | p99 | max |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for robot_id, s in rt["summaries"].items():
        lat = s.get("latency_ms") or {}
        sz = sizes.get(robot_id, [0])
        lines.append(
            f"| {robot_id} | {s['frames']} | {s['keyframes']} | {len(sizes.get(robot_id, []))} | "
            f"{np.mean(sz):,.0f} | {max(sz):,} | {lat.get('p50', 'n/a')} | {lat.get('p95', 'n/a')} | "
            f"{lat.get('p99', 'n/a')} | {lat.get('max', 'n/a')} |"
        )
    all_sizes = [len(p) for _, p in payloads]
    mean = float(np.mean(all_sizes)) if all_sizes else 0.0
    verdict = "met" if mean <= GOAL_BYTES else "NOT met"
    lines += [
        "",
        f"- bytes per keyframe, all robots: mean {mean:,.0f} (goal <= {GOAL_BYTES:,}: {verdict}).",
        f"- real time: {rt['wall_s']:.0f} s wall for {args.frames} frames per robot; total outbox backlog "
        f"max {rt['max_backlog']} keyframes, trend {rt['slope']:+.3f} keyframes/s "
        f"({rt['heartbeats']} heartbeats); "
        + ("the server keeps up (the backlog does not grow)." if rt["slope"] < 0.05 and rt["max_backlog"] <= 8
           else "the backlog GROWS: the server does not keep up."),
        f"- ingest throughput (fresh server, {tp['n']} keyframes re-published as fast as possible): "
        f"{tp['kf_per_s']:.0f} keyframes/s, {tp['mb_per_s']:.1f} MB/s "
        f"({tp['seconds']:.2f} s to the last ack; {tp['stored']} stored).",
        "- latency: edge's first publish -> ack received (ack after the SQLite commit, synchronous=FULL).",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
