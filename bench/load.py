"""Ingest load: N robots replaying recorded keyframes into one or two map servers.

Real processes on loopback: one ``wardmap router`` and one or two ``wardmap server`` (default
settings, mapping stage included) on one store, SQLite (one server only: a file is one
server's) or a fresh PostgreSQL database (``--postgres URL`` of a database the bench may create
databases from, e.g. ``postgresql://postgres@127.0.0.1:5432/postgres``). The keyframes are
recorded once (hospital_loop seed 0, the first ``--frames`` frames through the edge tracker,
``tools/keyframes.py``; cached under ``out/load/``) and encoded for every robot before the run,
so the load generator costs little: one zenoh session in this process with one publisher per
robot, each putting ``--rate`` keyframes a second for ``--seconds`` on a fixed schedule, at a
phase of its own within the period (uniform, seeded), as independent robots are (all in step,
a server sees bursts of every robot's keyframe at once).

Reported per run: keyframes offered and acked per second (an ack comes after the commit; with
two servers the first ``stored``/``duplicate`` ack counts), ack latency from the put (p50, p99),
the writer's mapping throughput (keyframes through perception per second, from its
``/metrics``) and its mapping backlog at the start and the end of the run (growing: mapping
cannot keep up with this load). Wall-clock figures on a shared host are upper bounds.

    python bench/load.py [--robots 8 [32 ...]] [--rate 2] [--seconds 20] [--postgres URL]
                         [--write BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import queue
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _procs import free_port, start, stop
from _report import git_rev, machine, publish

from wardmap.shared import wire
from wardmap.shared.zenoh_config import client_config, keyframe_key

CACHE = Path(__file__).resolve().parents[1] / "out" / "load"


def recorded(frames: int) -> list[wire.KeyframeMsg]:
    """The recorded keyframes (made once, then read from ``out/load/``)."""
    from wardmap.sim.runner import generate
    from wardmap.tools.keyframes import cache_keyframes

    run = CACHE / f"hospital_loop_s0_{frames}"
    if not (run / "sim.json").is_file():
        print(f"simulating {frames} frames of hospital_loop ...", file=sys.stderr)
        generate("hospital_loop", 0, run, frames=frames, overwrite=True)
    cache = cache_keyframes(run, CACHE / f"keyframes_{frames}", robot_id="r", session_id="s")
    return [wire.decode_keyframe(cache.payload(i)) for i in range(len(cache.stamps))]


def payloads(base: list[wire.KeyframeMsg], robots: int, n: int) -> list[list[bytes]]:
    """``n`` encoded keyframes per robot: the recording repeated, each robot its own id and
    session, seq 0..n-1, stamps one second apart."""
    t0 = base[0].stamp
    return [[wire.encode(dataclasses.replace(base[i % len(base)], robot_id=f"load{r:03d}",
                                             session_id=f"load{r:03d}-s", seq=i, stamp=t0 + i))
             for i in range(n)] for r in range(robots)]


def _metric(url: str, name: str) -> float:
    for line in httpx.get(f"{url}/metrics", timeout=10).text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[-1])
    return 0.0


def _writer(urls: list[str]) -> str:
    for url in urls:
        if httpx.get(f"{url}/readyz", timeout=10).json().get("mapping", "writer") == "writer":
            return url
    raise SystemExit("no server holds the writer lease")


def run_once(db: str, servers: int, robots: int, rate: float, seconds: float,
             messages: list[list[bytes]], config: Path | None = None) -> dict[str, Any]:
    """One run; its figures (see the module docstring)."""
    import zenoh

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs = [start(["router", "--listen", endpoint], f"router listening on {endpoint}")]
    urls = []
    try:
        for i in range(servers):
            port = free_port()
            url = f"http://127.0.0.1:{port}"
            procs.append(start(["server", "--connect", endpoint, "--db", db, "--http", f"127.0.0.1:{port}",
                                 "--insecure-loopback", "--name", f"load-{i}",
                                 *(["--config", str(config)] if config is not None else [])],
                                f"server ready: {url}"))
            urls.append(url)
        writer = _writer(urls)
        sent: dict[tuple[str, int], float] = {}
        acked: dict[tuple[str, int], float] = {}
        acks: queue.Queue[tuple[float, bytes]] = queue.Queue()
        conf = zenoh.Config.from_json5(json.dumps(client_config([endpoint])))
        with zenoh.open(conf) as session:
            sub = session.declare_subscriber("wardmap/v1/robot/*/ack",
                                             lambda s: acks.put((time.monotonic(), s.payload.to_bytes())))
            pubs = [session.declare_publisher(keyframe_key(f"load{r:03d}"),
                                              reliability=zenoh.Reliability.RELIABLE,
                                              congestion_control=zenoh.CongestionControl.BLOCK)
                    for r in range(robots)]
            time.sleep(1.0)  # the servers' subscriptions reach the publishers
            n = len(messages[0])
            mapped0, backlog0 = _metric(writer, "wardmap_mapping_keyframes_total"), _metric(
                writer, "wardmap_mapping_backlog")
            # Robots are not in step: each puts at its own phase within the period (seeded).
            phase = np.random.default_rng(0).uniform(0.0, 1.0 / rate, robots)
            schedule = sorted((i / rate + phase[r], r, i) for r in range(robots) for i in range(n))
            t0 = time.monotonic()
            for due, r, i in schedule:
                time.sleep(max(0.0, t0 + due - time.monotonic()))  # the fixed schedule
                sent[(f"load{r:03d}", i)] = time.monotonic()
                pubs[r].put(messages[r][i])
            deadline = time.monotonic() + 60
            while len(acked) < len(sent) and time.monotonic() < deadline:
                try:
                    at, data = acks.get(timeout=1)
                except queue.Empty:
                    continue
                ack = wire.decode_ack(data)
                if ack.status in ("stored", "duplicate"):
                    acked.setdefault((ack.robot_id, ack.seq), at)
            last = max(acked.values(), default=t0)
            elapsed = time.monotonic() - t0
            mapped, backlog = _metric(writer, "wardmap_mapping_keyframes_total"), _metric(
                writer, "wardmap_mapping_backlog")
            sub.undeclare()
            for pub in pubs:
                pub.undeclare()
        latency_ms = np.asarray([acked[k] - sent[k] for k in acked]) * 1e3
        return {"offered": len(sent) / (n / rate), "acked": len(acked), "sent": len(sent),
                "acked_rate": len(acked) / max(last - t0, 1e-9),
                "p50": float(np.percentile(latency_ms, 50)) if len(latency_ms) else float("nan"),
                "p99": float(np.percentile(latency_ms, 99)) if len(latency_ms) else float("nan"),
                "mapping_rate": (mapped - mapped0) / elapsed, "backlog": (backlog0, backlog)}
    finally:
        for proc in reversed(procs):
            stop(proc)


def _postgres_db(admin_url: str, name: str, drop: bool = False) -> str:
    import psycopg

    with psycopg.connect(admin_url, autocommit=True) as conn:
        conn.execute(f"DROP DATABASE IF EXISTS {name}" if drop else f"CREATE DATABASE {name}")
    return admin_url.rsplit("/", 1)[0] + "/" + name


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[8], help="robot counts to run (each)")
    ap.add_argument("--rate", type=float, default=2.0, help="keyframes per second per robot")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--frames", type=int, default=60, help="simulated frames recorded once")
    ap.add_argument("--postgres", metavar="URL", help="a database to create the runs' databases from")
    ap.add_argument("--no-mapping", action="store_true",
                    help="servers only store (``[pipeline] enabled = false``): ingest alone")
    ap.add_argument("--write", type=Path, default=None, help="write the table into this markdown file")
    args = ap.parse_args()
    base = recorded(args.frames)
    runs: list[tuple[str, int]] = [("sqlite", 1)]
    if args.postgres:
        runs += [("postgres", 1), ("postgres", 2)]
    rows = []
    for robots in args.robots:
        messages = payloads(base, robots, int(args.seconds * args.rate))
        for kind, servers in runs:
            with tempfile.TemporaryDirectory() as tmp:
                config = None
                if args.no_mapping:
                    config = Path(tmp) / "server.toml"
                    config.write_text("[pipeline]\nenabled = false\n")
                name = f"wardmap_load_{os.getpid()}_{servers}"
                db = f"sqlite:///{tmp}/map.db" if kind == "sqlite" else _postgres_db(args.postgres, name)
                try:
                    print(f"{robots} robots, {kind}, {servers} server(s) ...", file=sys.stderr)
                    r = run_once(db, servers, robots, args.rate, args.seconds, messages, config)
                finally:
                    if kind == "postgres":
                        _postgres_db(args.postgres, name, drop=True)
            rows.append(f"| {kind} | {servers} | {robots} x {args.rate:g}/s | {r['offered']:.1f} | "
                        f"{r['acked']}/{r['sent']} | {r['acked_rate']:.1f} | {r['p50']:.0f} | "
                        f"{r['p99']:.0f} | "
                        + ("off | off |" if args.no_mapping else
                           f"{r['mapping_rate']:.2f} | {r['backlog'][0]:.0f} -> {r['backlog'][1]:.0f} |"))
            print(rows[-1], file=sys.stderr)
    cmd = (f"python bench/load.py --robots {' '.join(map(str, args.robots))} --rate {args.rate:g} "
           f"--seconds {args.seconds:g}"
           + (" --postgres URL" if args.postgres else "") + (" --no-mapping" if args.no_mapping else "")
           + " --write BENCHMARKS.md")
    body = "\n".join([
        "## Ingest load: robots into one and two servers" + (", mapping off" if args.no_mapping else "")
        + " (issue 43)",
        "",
        f"Command: `{cmd}`  ",
        f"Machine: {machine()}; commit {git_rev()}. Real `wardmap router` and `wardmap server` (default "
        f"settings, mapping stage {'off: ingest alone' if args.no_mapping else 'on'}) on loopback; "
        "recorded keyframes of hospital_loop (about 100 KB each) put on a fixed schedule, each robot at "
        "its own phase within the period; an ack "
        "comes after the commit. A shared 2-core host: upper bounds.",
        "",
        "| store | servers | robots | offered kf/s | acked | acked kf/s | ack p50 ms | ack p99 ms | "
        "writer mapping kf/s | writer backlog start -> end |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        "Goals of issue 43 (PostgreSQL): 32 robots at 2 kf/s with ack p99 <= 100 ms and no growing "
        "backlog; two perception workers >= 1.8x one (perception is not shared out between servers "
        "yet: only the writer maps); the association writer alone >= 60 kf/s (not measured here).",
    ])
    publish(body, args.write, "load-ingest" if args.no_mapping else "load")


if __name__ == "__main__":
    main()
