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
two servers the first ``stored``/``duplicate`` ack counts), ack latency from the put (p50, p99;
in brackets the p99 of the keyframes put after the first :data:`WARMUP_S` seconds: every robot's
first keyframe comes while the servers' mapping stage runs for the first time, and the acks of
that second (up to 150 ms, measured) can be most of a run's worst percent),
the writer's mapping throughput (keyframes its mapping stage took in per second, from its
``/metrics``) and its mapping backlog at the start and the end of the run (growing: mapping
cannot keep up with this load), and the time per keyframe of each mapping step during the run
(back-end and association on the writer; perception wherever it ran: the writer's own, or the
workers' busy seconds over the keyframes they measured). ``--perception-workers 0 1 2`` runs
each case with that many perception worker processes per server (``wardmap server
--perception-workers``). Wall-clock figures on a shared host are upper bounds.

``--backlog K`` (PostgreSQL) also measures the parts of the mapping stage apart, after the server
runs, on K keyframes of the first ``--robots`` count stored beforehand, in this process, without
servers or ingest: the perception workers alone (for each
``--perception-workers`` count > 0, a fresh database: the keyframes stored, then the workers
started, timed from the moment every worker has its segmenter loaded and works until every
keyframe has a result, over the keyframes still without one then: the steady rate of that many
workers, without the start-up or the storing), then the back-end alone over them,
then the association writer alone (the mapping stage started with every measurement and every
graph pose already stored, timed from its start to idle: association, object-map writes and
the commits).

    python bench/load.py [--robots 8 [32 ...]] [--rate 2] [--seconds 20] [--postgres URL]
                         [--perception-workers 0 [1 2]] [--backlog K [--repeat R]] [--write BENCHMARKS.md]
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


def _metrics(url: str) -> dict[str, float]:
    """Every sample of the server's ``/metrics`` (``name{labels}`` -> value)."""
    out = {}
    for line in httpx.get(f"{url}/metrics", timeout=10).text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            out[name] = float(value)
    return out


def _metric(url: str, name: str) -> float:
    return _metrics(url).get(name, 0.0)


def _step_ms(before: list[dict[str, float]], after: list[dict[str, float]]) -> dict[str, float]:
    """Mean milliseconds per keyframe of each mapping step between two scrapes of every server:
    ``backend``, ``association`` (the writer's histograms) and ``perception`` (the writer's own
    measuring and every server's workers together: busy seconds over keyframes done)."""
    def delta(name: str) -> float:
        return sum(a.get(name, 0.0) - b.get(name, 0.0) for a, b in zip(after, before, strict=True))

    out = {}
    for step in ("backend", "association"):
        n = delta(f'wardmap_mapping_stage_seconds_count{{stage="{step}"}}')
        seconds = delta(f'wardmap_mapping_stage_seconds_sum{{stage="{step}"}}')
        out[step] = 1e3 * seconds / n if n else float("nan")
    busy = sum(a[k] - b.get(k, 0.0) for a, b in zip(after, before, strict=True) for k in a
               if k.startswith("wardmap_perception_busy_seconds_total{"))
    done = delta("wardmap_perception_keyframes_total") + delta(
        'wardmap_mapping_stage_seconds_count{stage="perception"}')
    busy += delta('wardmap_mapping_stage_seconds_sum{stage="perception"}')
    out["perception"] = 1e3 * busy / done if done else float("nan")
    return out


def _writer(urls: list[str]) -> str:
    for url in urls:
        if httpx.get(f"{url}/readyz", timeout=10).json().get("mapping", "writer") == "writer":
            return url
    raise SystemExit("no server holds the writer lease")


WARMUP_S = 1.0
"""Seconds at the start of a run left out of the bracketed p99 (module docstring)."""


def run_once(db: str, servers: int, robots: int, rate: float, seconds: float,
             messages: list[list[bytes]], config: Path | None = None, workers: int = 0) -> dict[str, Any]:
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
                                 "--perception-workers", str(workers),
                                 *(["--config", str(config)] if config is not None else [])],
                                f"server ready: {url}"))
            urls.append(url)
        writer = _writer(urls)
        deadline = time.monotonic() + 120
        for url in urls if workers else []:  # every worker has its segmenter and reports from its loop
            while (sum(k.startswith("wardmap_perception_busy_seconds_total{") for k in _metrics(url))
                   < workers and time.monotonic() < deadline):
                time.sleep(0.2)
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
            scrape0 = [_metrics(url) for url in urls]
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
            steps = _step_ms(scrape0, [_metrics(url) for url in urls])
            sub.undeclare()
            for pub in pubs:
                pub.undeclare()
        latency_ms = np.asarray([acked[k] - sent[k] for k in acked]) * 1e3
        steady_ms = np.asarray([acked[k] - sent[k] for k in acked if sent[k] - t0 >= WARMUP_S]) * 1e3
        return {"offered": len(sent) / (n / rate), "acked": len(acked), "sent": len(sent),
                "acked_rate": len(acked) / max(last - t0, 1e-9),
                "p50": float(np.percentile(latency_ms, 50)) if len(latency_ms) else float("nan"),
                "p99": float(np.percentile(latency_ms, 99)) if len(latency_ms) else float("nan"),
                "p99_steady": float(np.percentile(steady_ms, 99)) if len(steady_ms) else float("nan"),
                "mapping_rate": (mapped - mapped0) / elapsed, "backlog": (backlog0, backlog), "steps": steps,
                "load": os.getloadavg()[0]}
    finally:
        for proc in reversed(procs):
            stop(proc)


def _postgres_db(admin_url: str, name: str, drop: bool = False) -> str:
    import psycopg

    with psycopg.connect(admin_url, autocommit=True) as conn:
        conn.execute(f"DROP DATABASE IF EXISTS {name}" if drop else f"CREATE DATABASE {name}")
    return admin_url.rsplit("/", 1)[0] + "/" + name


def backlog_parts(admin_url: str, base: list[wire.KeyframeMsg], robots: int, n: int,
                  workers: list[int], repeat: int = 1) -> tuple[list[str], dict[str, float]]:
    """The ``--backlog`` rows (see the module docstring): perception workers alone for each count
    (the counts in turn, ``repeat`` times), then the back-end alone and the association writer
    alone on the last database; and their rates (kf/s) by part: ``"workers N"`` (the median of
    its runs), ``"backend"``, ``"writer"``."""
    from wardmap.server.backend.stage import BackendStage
    from wardmap.server.mapping import MapPipeline, PipelineConfig
    from wardmap.server.mapping.stage import CURSOR_NAME
    from wardmap.server.mapping.workers import MappingConfig, PerceptionWorkers
    from wardmap.server.objectmap import ObjectMap
    from wardmap.server.perception.config import PerceptionConfig
    from wardmap.server.store import open_store

    messages = payloads(base, robots, n)
    ordered = [messages[r][i] for i in range(n) for r in range(robots)]  # robots interleaved, as they arrive
    keyframes = [(wire.decode_keyframe(m), m) for m in ordered]
    total = len(keyframes)
    rows = []
    rates: dict[str, float] = {}
    runs: dict[int, list[float]] = {}
    name = f"wardmap_backlog_{os.getpid()}"
    db = ""
    for count in ([w for w in workers if w > 0] or [1]) * repeat:
        if db:
            _postgres_db(admin_url, name, drop=True)
        db = _postgres_db(admin_url, name)
        cfg = MappingConfig(perception_workers=count)
        with open_store(db) as store:
            for msg, payload in keyframes:  # the backlog, stored before any worker runs
                store.insert(msg, payload, time.time())
            pool = PerceptionWorkers(db, config=cfg, perception=PerceptionConfig(), name="bench")
            pool.start()
            try:
                deadline = time.monotonic() + 120
                while len(pool.counters().busy_s) < count and time.monotonic() < deadline:
                    time.sleep(0.01)  # every worker has its segmenter and reports from its loop
                # timed from the moment all of them work: what the first one did alone is left out
                t0 = time.monotonic()
                timed = store.count_unperceived(CURSOR_NAME)
                while store.count_unperceived(CURSOR_NAME) > 0:
                    time.sleep(0.1)  # a query a tenth of a second: little CPU taken from the workers
                elapsed = time.monotonic() - t0
                c = pool.counters()
            finally:
                pool.stop()
        done = max(c.measured + sum(c.failures.values()), 1)
        busy_ms, cpu_ms = 1e3 * sum(c.busy_s.values()) / done, 1e3 * sum(c.cpu_s.values()) / done
        runs.setdefault(count, []).append(timed / elapsed)
        rates[f"workers {count}"] = float(np.median(runs[count]))
        rows.append(f"| perception workers alone | {count} | {timed} of {total} | {timed / elapsed:.1f} | "
                    f"{busy_ms:.0f} | {cpu_ms:.0f} | {os.getloadavg()[0]:.2f} |")
        print(rows[-1], file=sys.stderr)
    try:
        with open_store(db) as store:
            backend = BackendStage(store)
            t0, cpu0 = time.monotonic(), _cpu_s()
            backend.start()
            last = store.next_keyframes(0, total)[-1].rowid
            while backend.cursor() < last:
                time.sleep(0.05)
            elapsed, cpu = time.monotonic() - t0, _cpu_s() - cpu0
            backend.stop()
            rates["backend"] = total / elapsed
            rows.append(f"| back-end alone | - | {total} | {total / elapsed:.1f} | "
                        f"{1e3 * elapsed / total:.0f} | {1e3 * cpu / total:.0f} | {os.getloadavg()[0]:.2f} |")
            print(rows[-1], file=sys.stderr)
            pipe = MapPipeline(store, ObjectMap(store),
                               config=PipelineConfig(close_idle_s=0.0, checkpoint_s=0.0),
                               backend=BackendStage(store),
                               shared=MappingConfig(perception_workers=1, wait_s=50.0))
            pipe.start()
            t0, cpu0 = time.monotonic(), _cpu_s()
            if not pipe.wait_idle(600):
                raise SystemExit("the association writer did not finish in 600 s")
            elapsed, cpu = time.monotonic() - t0, _cpu_s() - cpu0
            counters = pipe.counters()
            pipe.stop()
        rates["writer"] = total / elapsed
        rows.append(f"| association writer alone | - | {total} ({counters.mapped} on the map) | "
                    f"{total / elapsed:.1f} | {1e3 * elapsed / total:.1f} | {1e3 * cpu / total:.1f} | "
                    f"{os.getloadavg()[0]:.2f} |")
        print(rows[-1], file=sys.stderr)
    finally:
        _postgres_db(admin_url, name, drop=True)
    return rows, rates


def _cpu_s() -> float:
    """CPU seconds of this process so far (every thread; not the database server's)."""
    import resource

    use = resource.getrusage(resource.RUSAGE_SELF)
    return use.ru_utime + use.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[8], help="robot counts to run (each)")
    ap.add_argument("--rate", type=float, default=2.0, help="keyframes per second per robot")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--frames", type=int, default=60, help="simulated frames recorded once")
    ap.add_argument("--postgres", metavar="URL", help="a database to create the runs' databases from")
    ap.add_argument("--no-mapping", action="store_true",
                    help="servers only store (``[pipeline] enabled = false``): ingest alone")
    ap.add_argument("--perception-workers", type=int, nargs="+", default=[0], metavar="N",
                    help="perception worker processes per server (each count runs every case)")
    ap.add_argument("--backlog", type=int, metavar="K",
                    help="instead of servers: the mapping stage's parts apart on K stored keyframes "
                         "(PostgreSQL)")
    ap.add_argument("--repeat", type=int, default=1, metavar="R",
                    help="--backlog: run the perception workers alone R times for each count, in turn "
                         "(a shared host's noise; the target uses the medians)")
    ap.add_argument("--write", type=Path, default=None, help="write the table into this markdown file")
    args = ap.parse_args()
    if args.repeat < 1:
        raise SystemExit("--repeat must be >= 1")
    base = recorded(args.frames)
    if args.backlog and not args.postgres:
        raise SystemExit("--backlog needs --postgres")
    runs: list[tuple[str, int]] = [("sqlite", 1)]
    if args.postgres:
        runs += [("postgres", 1), ("postgres", 2)]
    rows = []
    for robots in args.robots:
        messages = payloads(base, robots, int(args.seconds * args.rate))
        for workers in args.perception_workers:
            for kind, servers in runs:
                with tempfile.TemporaryDirectory() as tmp:
                    config = None
                    if args.no_mapping:
                        config = Path(tmp) / "server.toml"
                        config.write_text("[pipeline]\nenabled = false\n")
                    name = f"wardmap_load_{os.getpid()}_{servers}"
                    db = f"sqlite:///{tmp}/map.db" if kind == "sqlite" else _postgres_db(args.postgres, name)
                    try:
                        print(f"{robots} robots, {kind}, {servers} server(s), {workers} worker(s) each ...",
                              file=sys.stderr)
                        r = run_once(db, servers, robots, args.rate, args.seconds, messages, config, workers)
                    finally:
                        if kind == "postgres":
                            _postgres_db(args.postgres, name, drop=True)
                steps = r["steps"]
                rows.append(f"| {kind} | {servers} | {workers} | {robots} x {args.rate:g}/s | "
                            f"{r['offered']:.1f} | "
                            f"{r['acked']}/{r['sent']} | {r['acked_rate']:.1f} | {r['p50']:.0f} | "
                            f"{r['p99']:.0f} ({r['p99_steady']:.0f}) | "
                            + ("off | off | off |" if args.no_mapping else
                               f"{r['mapping_rate']:.2f} | {r['backlog'][0]:.0f} -> {r['backlog'][1]:.0f} | "
                               f"{steps['backend']:.0f} / {steps['perception']:.0f} / "
                               f"{steps['association']:.0f} |")
                            + f" {r['load']:.2f} |")
                print(rows[-1], file=sys.stderr)
    parts: list[str] = []
    rates: dict[str, float] = {}
    if args.backlog:
        robots = args.robots[0]
        parts, rates = backlog_parts(args.postgres, base, robots, max(1, args.backlog // robots),
                                     args.perception_workers, args.repeat)
    cmd = (f"python bench/load.py --robots {' '.join(map(str, args.robots))} --rate {args.rate:g} "
           f"--seconds {args.seconds:g}"
           + (" --postgres URL" if args.postgres else "") + (" --no-mapping" if args.no_mapping else "")
           + (f" --perception-workers {' '.join(map(str, args.perception_workers))}"
              if args.perception_workers != [0] else "")
           + (f" --backlog {args.backlog}" if args.backlog else "")
           + (f" --repeat {args.repeat}" if args.repeat > 1 else "") + " --write BENCHMARKS.md")
    body = "\n".join([
        "## Ingest load: robots into one and two servers" + (", mapping off" if args.no_mapping else "")
        + " (issue 43)",
        "",
        f"Command: `{cmd}`  ",
        f"Machine: {machine()}; commit {git_rev()}. Real `wardmap router` and `wardmap server` (default "
        f"settings, mapping stage {'off: ingest alone' if args.no_mapping else 'on'}) on loopback; "
        "recorded keyframes of hospital_loop (about 100 KB each) put on a fixed schedule, each robot at "
        "its own phase within the period; an ack "
        "comes after the commit. A shared 2-core host: upper bounds. Mapping ms per keyframe: "
        "back-end / perception (wherever it ran) / association; load avg: 1-minute, at the end of the run.",
        "",
        "| store | servers | perception workers per server | robots | offered kf/s | acked | acked kf/s | "
        f"ack p50 ms | ack p99 ms (after {WARMUP_S:g} s) | writer mapping kf/s | "
        "writer backlog start -> end | mapping ms/kf | load avg |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        *rows,
    ])
    if parts:
        stored = args.robots[0] * max(1, args.backlog // args.robots[0])
        body += "\n".join([
            "", "",
            f"Mapping stage parts apart (`--backlog`): {stored} keyframes of "
            f"{args.robots[0]} robots stored beforehand in a fresh PostgreSQL database, no servers, "
            "no ingest. Perception workers: processes with the packaged network, started after the "
            "keyframes were stored, timed from the moment every one of them works (its segmenter "
            "loaded) to the last result, over the keyframes still without a result then (keyframes: "
            "timed of all); back-end: one BackendStage over them; association writer: the "
            "mapping stage with every measurement and graph pose stored, from start to idle (association, "
            "object-map writes, commits). CPU ms: the part's own process CPU per keyframe (not the "
            "database server's).",
            "",
            "| part | workers | keyframes | kf/s | wall ms/kf | CPU ms/kf | load avg |",
            "|---|---|---|---|---|---|---|",
            *parts,
            "",
            "Issue 43 targets (PostgreSQL): two perception workers >= 1.8x one: "
            + (f"{rates['workers 2'] / rates['workers 1']:.2f}x (workers alone"
               + (f", medians of {args.repeat} runs each" if args.repeat > 1 else "") + ")"
               if "workers 1" in rates and "workers 2" in rates else "not run")
            + f"; the association writer alone >= 60 kf/s: {rates.get('writer', float('nan')):.1f} kf/s.",
        ])
    publish(body, args.write, "load-ingest" if args.no_mapping else "load")


if __name__ == "__main__":
    main()
