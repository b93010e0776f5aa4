"""How fast ``/readyz`` tells the truth about the router: real ``wardmap router`` and
``wardmap server`` processes on loopback.

The server starts once (default settings, mapping stage included). Then ``--rounds`` times:
SIGKILL the router and poll ``/readyz`` every 5 ms until it answers 503 (``down``: from the
kill to the first 503); start a router on the same endpoint and poll until ``/readyz`` answers
200 (``up``: from the router's ready line to the first 200, i.e. zenoh's reconnection plus one
probe). Times are wall clock on this machine, polling included (so at most 5 ms high).

    python bench/health.py [--rounds 10] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import signal
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _procs import free_port, start, stop
from _report import git_rev, machine, publish

POLL_S = 0.005


def _until(http: httpx.Client, status: int, timeout_s: float = 30.0) -> float:
    t0 = time.monotonic()
    while http.get("/readyz").status_code != status:
        if time.monotonic() - t0 > timeout_s:
            raise SystemExit(f"/readyz did not answer {status} within {timeout_s} s")
        time.sleep(POLL_S)
    return time.monotonic()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--write", type=Path, default=None, help="write the table into this markdown file")
    args = ap.parse_args()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    down, up = [], []
    with tempfile.TemporaryDirectory() as tmp:
        router = start(["router", "--listen", endpoint], f"router listening on {endpoint}")
        server = start(["server", "--connect", endpoint, "--db", f"sqlite:///{tmp}/map.db", "--http",
                         f"127.0.0.1:{port}"], f"server ready: {url}")
        try:
            with httpx.Client(base_url=url, timeout=5) as http:
                _until(http, 200)
                for _ in range(args.rounds):
                    router.send_signal(signal.SIGKILL)
                    killed = time.monotonic()
                    router.wait(10)
                    down.append(_until(http, 503) - killed)
                    router = start(["router", "--listen", endpoint], f"router listening on {endpoint}")
                    listening = time.monotonic()
                    up.append(_until(http, 200) - listening)
        finally:
            stop(server)
            stop(router)
    rows = []
    for name, values in (("router SIGKILLed -> first 503", down), ("router listening -> first 200", up)):
        ms = np.asarray(values) * 1e3
        rows.append(f"| {name} | {len(ms)} | {np.median(ms):.0f} | {ms.max():.0f} |")
    body = "\n".join([
        "## Readiness follows the router (issue 43)",
        "",
        f"Command: `python bench/health.py --rounds {args.rounds} --write BENCHMARKS.md`  ",
        f"Machine: {machine()}; commit {git_rev()}. Real `wardmap router` and `wardmap server` "
        f"(default settings) processes on loopback; `/readyz` polled every {POLL_S * 1e3:.0f} ms.",
        "",
        "| event | rounds | median ms | max ms |",
        "|---|---|---|---|",
        *rows,
        "",
        "The goal of issue 43 is 503 within 2 s of the router dying.",
    ])
    publish(body, args.write, "health")


if __name__ == "__main__":
    main()
