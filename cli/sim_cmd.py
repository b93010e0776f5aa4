"""``wardmap sim``: generate a simulated hospital data set."""

from __future__ import annotations

import argparse
import time

from wardmap.cli.progress import Progress


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "sim",
        help="generate a simulated hospital data set",
        description="Render a scenario of the simulated hospital into a data set folder "
        "(TUM RGB-D layout extended with thermal, odometry and ground truth).",
    )
    p.add_argument("--list", action="store_true", help="list the scenarios and exit")
    p.add_argument("--scenario", metavar="NAME", help="scenario name (see --list)")
    p.add_argument("--seed", type=int, default=0, help="world and noise seed (default 0)")
    p.add_argument("--out", metavar="DIR", help="output folder (created; must be empty)")
    p.add_argument("--frames", type=int, metavar="K", help="stop after K camera frames per robot")
    p.add_argument("--overwrite", action="store_true", help="allow a non-empty output folder")
    p.add_argument("--rgb-readout-ms", type=float, default=0.0, metavar="MS",
                   help="render the colour camera with a rolling shutter of this readout time, first row "
                        "to last (default 0: global shutter); the calibration records it")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from wardmap.shared.errors import SimulationError
    from wardmap.sim.scenarios import SCENARIOS

    if args.list:
        width = max(len(n) for n in SCENARIOS)
        for name, spec in SCENARIOS.items():
            print(f"{name:<{width}}  {spec.description}")
        return 0
    if not args.scenario or not args.out:
        raise SimulationError("--scenario NAME and --out DIR are required (or --list)")

    from wardmap.sim.runner import generate
    from wardmap.sim.sensors import SensorRig

    rig = SensorRig(rgb_readout_s=args.rgb_readout_ms / 1000.0)
    started = time.monotonic()
    with Progress("frames") as bar:
        summaries = generate(args.scenario, args.seed, args.out, frames=args.frames, overwrite=args.overwrite,
                             progress=bar.update, rig=rig)
    elapsed = time.monotonic() - started
    for s in summaries:
        print(f"{s.name}: {s.frames} frames, {s.duration_s:.1f} s, {s.length_m:.1f} m -> {s.path}")
    total = sum(s.frames for s in summaries)
    print(f"done: {total} frames in {elapsed:.1f} s ({total / max(elapsed, 1e-9):.1f} frames/s)")
    return 0
