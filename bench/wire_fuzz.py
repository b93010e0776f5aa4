"""Wire fuzzing (issue 39): ``--n`` seeded malformed payloads through the decoder ingest uses.

Each payload is one mutation (``tests/factories.py`` ``mutate``: bit flips, truncation,
inserted bytes, random bytes, a field replaced, deleted or added) of a valid keyframe (with
and without thermal and intrinsics), an ack, a heartbeat or a raster bomb (a keyframe whose
headers declare 8192x8192 images). Each is decoded with ``wire.decode_keyframe`` as
``server/ingest.py`` does: a keyframe it would store, a rejection it would count under
``wire_reason(field)``, or a crash (any other exception). The table gives the counts, the
reasons, and the slowest decode.

    python bench/wire_fuzz.py [--n 100000] [--seed 0] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT / "tests"))
from _report import git_rev, machine, publish  # noqa: E402
from factories import full_keyframe, mutate, raster_bomb  # noqa: E402

from wardmap.server.ingest import wire_reason  # noqa: E402
from wardmap.shared import wire  # noqa: E402
from wardmap.shared.errors import WireError  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--write", type=Path, default=None, help="write the table into this markdown file")
    args = ap.parse_args()

    rng = np.random.default_rng(args.seed)
    bases = [
        wire.encode(full_keyframe(rng, thermal=True, intrinsics=True)),
        wire.encode(full_keyframe(rng, thermal=False, intrinsics=False, base=False)),
        wire.encode(wire.AckMsg("robot_0", "s1", 3, "stored")),
        wire.encode(wire.HeartbeatMsg("robot_0", "s1", 1.7e9, {"fps": 10.0})),
        raster_bomb(rng),
    ]
    load_before = os.getloadavg()[0]
    outcomes: Counter[str] = Counter()
    reasons: Counter[str] = Counter()
    crashes: list[str] = []
    slowest = 0.0
    t0 = time.perf_counter()
    for trial in range(args.n):
        payload = mutate(bases[trial % len(bases)], rng, random_payloads=True)
        t = time.perf_counter()
        try:
            wire.decode_keyframe(payload)
            outcomes["valid keyframe (would be stored)"] += 1
        except WireError as exc:
            outcomes["rejected (WireError, counted)"] += 1
            reasons[wire_reason(exc.field)] += 1
        except Exception as exc:  # the property under test: none
            outcomes["crash (any other exception)"] += 1
            if len(crashes) < 10:
                crashes.append(f"trial {trial}: {type(exc).__name__}: {exc}"[:200])
        slowest = max(slowest, time.perf_counter() - t)
    total_s = time.perf_counter() - t0
    outcomes.setdefault("crash (any other exception)", 0)

    rows = ["| outcome | payloads |", "|---|---|"]
    rows += [f"| {name} | {n} |" for name, n in sorted(outcomes.items())]
    rows += ["", "| rejection reason | payloads |", "|---|---|"]
    rows += [f"| `{name}` | {n} |" for name, n in reasons.most_common()]
    body = "\n".join([
        "## Wire fuzzing (issue 39)",
        "",
        f"Command: `python bench/wire_fuzz.py --n {args.n} --seed {args.seed} --write BENCHMARKS.md`  ",
        f"Machine: {machine()}; commit {git_rev()}; 1-min load average {load_before:.1f} before, "
        f"{os.getloadavg()[0]:.1f} after (a shared host: upper bounds).",
        "",
        f"{args.n} payloads in {total_s:.1f} s (mean {1e3 * total_s / args.n:.2f} ms with the mutation; "
        f"slowest decode {1e3 * slowest:.1f} ms); every one is a keyframe or a counted rejection "
        f"unless listed as a crash.",
        "",
        *rows,
        *([""] + [f"- {c}" for c in crashes] if crashes else []),
    ])
    publish(body, args.write, "wire_fuzz")
    return 1 if crashes else 0


if __name__ == "__main__":
    sys.exit(main())
