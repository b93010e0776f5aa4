"""The web page in Chromium: first paint of a 10,000-object map and live-update latency.

Fills a temporary store with ``--objects`` objects (``bench/api.py``'s ``fill``: seeded random
poses over a 200 m x 100 m floor, every class), serves ``MapServer(url).app`` under uvicorn on
a loopback port in this process (the writes below must reach the server's object map, as the
map writer's do) and opens ``GET /`` in Debian's Chromium (headless, driven by Playwright).

- **first paint**: ``--loads`` fresh page loads (a new browser context each); the page's own
  ``performance.now()`` when every object of the snapshot is drawn, i.e. milliseconds from
  navigation start (HTML, scripts, the event stream's ``ready``, the object pages, one frame),
  and two parts of it the page times itself (``wardmap.state.timing``).
- **live update**: on one open page, ``--updates`` new objects written through the server's
  object map 200 ms apart; latency = the wall clock when the page drew the frame holding the
  object minus the wall clock just before the write started (so it includes the SQLite commit).

    python bench/web.py [--objects 10000] [--loads 5] [--updates 50] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import git_rev, machine, publish
from api import fill

from wardmap.server.app import MapServer
from wardmap.server.objectmap import ObjectState
from wardmap.server.store import open_store
from wardmap.server.tokens import create_token
from wardmap.shared.se3 import yaw_transform

GOAL_MS = 1000.0


def serve(url: str) -> tuple[str, MapServer, Any, threading.Thread]:
    import uvicorn

    root = MapServer(url)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    sock.listen(64)
    server = uvicorn.Server(uvicorn.Config(root.app, log_config=None, access_log=False, lifespan="on",
                                           timeout_graceful_shutdown=1))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    while not server.started:
        if not thread.is_alive():
            raise SystemExit("the server did not start")
        time.sleep(0.02)
    return f"http://127.0.0.1:{sock.getsockname()[1]}", root, server, thread


def stats(ms: list[float]) -> str:
    a = np.asarray(ms)
    return f"{np.median(a):.0f} | {np.percentile(a, 95):.0f} | {a.max():.0f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", type=int, default=10_000)
    ap.add_argument("--loads", type=int, default=5)
    ap.add_argument("--updates", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--write", type=Path, metavar="BENCHMARKS.md")
    args = ap.parse_args()
    chromium = shutil.which("chromium")
    if chromium is None:
        raise SystemExit("bench/web.py: no chromium on PATH (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as tmp:
        url = f"sqlite:///{tmp}/map.db"
        fill(url, args.objects, (200.0, 100.0), args.seed)
        with open_store(url) as store:  # the page authenticates as staff would, with a read token
            token = create_token(store, "read", "bench/web.py").text
        base, root, server, thread = serve(url)
        load_before = os.getloadavg()[0]
        paints: list[float] = []
        snapshots: list[float] = []
        draws: list[float] = []
        latencies: list[float] = []
        try:
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=chromium,
                                            args=["--no-sandbox", "--disable-dev-shm-usage"])
                for _ in range(args.loads):
                    ctx = browser.new_context(viewport={"width": 1280, "height": 800})
                    page = ctx.new_page()
                    page.goto(f"{base}/#token={token}")
                    page.wait_for_selector("body[data-ready='1']", timeout=60_000)
                    if page.evaluate("wardmap.state.objects.size") != args.objects:
                        raise SystemExit("the page did not load every object")
                    paints.append(page.evaluate("wardmap.state.firstPaintMs"))
                    timing = page.evaluate("wardmap.state.timing")
                    snapshots.append(timing["snapshotMs"])
                    draws.append(timing["drawMs"])
                    ctx.close()
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                page.goto(f"{base}/#token={token}")
                page.wait_for_selector("body[data-ready='1']", timeout=60_000)
                assert root.services is not None
                objects = root.services.objects
                rng = np.random.default_rng(args.seed + 1)
                for k in range(args.updates):
                    oid = args.objects + 1 + k
                    state = ObjectState(oid, "wheelchair", 0.8,
                                        yaw_transform(rng.uniform(0, 200), rng.uniform(0, 100), 0.0, 0.45),
                                        np.array([0.7, 0.7, 0.9]))
                    before_ms = time.time() * 1000.0
                    objects.upsert([state])
                    page.wait_for_function(f"wardmap.state.updatesDrawn.has({oid})", timeout=10_000)
                    latencies.append(page.evaluate(f"wardmap.state.updatesDrawn.get({oid})") - before_ms)
                    time.sleep(0.2)
                browser.close()
        finally:
            server.should_exit = True
            thread.join(15)
    version = chromium_version(chromium)
    body = "\n".join([
        "## Web page in Chromium (first paint, live updates)",
        "",
        f"`python bench/web.py --objects {args.objects} --loads {args.loads} --updates {args.updates}`: "
        f"{args.objects:,} objects over 200 m x 100 m, the server in-process on loopback, headless "
        f"{version} through Playwright. Goal: both under {GOAL_MS:.0f} ms (issue 40).",
        "",
        "| measure | n | median ms | p95 ms | max ms |",
        "|---|---|---|---|---|",
        f"| first paint: navigation start to every object drawn | {len(paints)} | {stats(paints)} |",
        f"| of which: object pages requested to parsed (`format=compact`, 10 in parallel) | {len(snapshots)} "
        f"| {stats(snapshots)} |",
        f"| of which: one frame drawing every object | {len(draws)} | {stats(draws)} |",
        f"| live update: write started to the frame that draws it | {len(latencies)} | {stats(latencies)} |",
        "",
        "Most of the first paint is the object pages: the server reads 10,000 objects from SQLite "
        "and encodes them on its one event-loop thread (`bench/api.py` times the same queries); drawing "
        "them is one frame.",
        "",
        f"Machine: {machine()}; commit {git_rev()}; 1-min load average {load_before:.1f} before (a shared "
        "host: upper bounds).",
    ])
    publish(body, args.write, "web")
    return 0


def chromium_version(path: str) -> str:
    import subprocess

    try:
        out = subprocess.run([path, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return "Chromium"
    return " ".join(out.split()[:2]) or "Chromium"


if __name__ == "__main__":
    sys.exit(main())
