"""A stuck subscriber, run as its own process: ``python tests/stuck_peer.py ENDPOINT [KEY]``.

It opens a zenoh client session on ``ENDPOINT`` (loopback, shared memory and multicast
scouting off), subscribes to ``KEY`` (default ``wardmap/**``) with a callback that blocks on
its first sample until stdin closes, prints ``stuck peer ready`` and waits for EOF on stdin.
While it blocks, zenoh stops reading its link, so the router's queue towards it fills. On EOF
it lets the callback go, closes the session and prints how many samples had reached the
callback before (1: it was stuck on the first).
"""

from __future__ import annotations

import json
import sys
import threading

import zenoh

from wardmap.shared.zenoh_config import client_config


def main(endpoint: str, key: str) -> None:
    release = threading.Event()
    seen = [0]

    def on_sample(_sample: zenoh.Sample) -> None:
        seen[0] += 1
        release.wait()  # stuck until the test closes stdin

    conf = zenoh.Config.from_json5(json.dumps(client_config([endpoint])))
    with zenoh.open(conf) as session, session.declare_subscriber(key, on_sample):
        print("stuck peer ready", flush=True)
        sys.stdin.read()
        while_stuck = seen[0]
        release.set()
    print(f"stuck peer saw {while_stuck}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else "wardmap/**")
