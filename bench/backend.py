"""SLAM back-end benchmark (issue 37): loop closures, the server's trajectory, anchoring, cost.

For every scenario (default: hospital_loop, two_robots, hospital_days, ward_chairs) and world
seed (default 2001-2005: evaluation worlds nobody tunes on; ``--tune``: 1001 1002), the
simulated data set is generated (cached under ``--data``) and every robot run is tracked by the
edge frontend offline (``wardmap.tools.keyframes``: the very keyframe messages the edge daemon
sends, with oracle labels as on a robot with a good network; cached under
``--data/keyframes``). The keyframes of all runs of a scenario go to one fresh
:class:`~wardmap.server.backend.core.BackendCore` in stamp order (the robots of two_robots
interleaved; hospital_days: day 1, then day 2 a day later). No run has a map pose: the first
session anchors the map. Scores (definitions in ``wardmap.tools.backend_eval``):

- closures: every loop edge that entered the pose graph (accepted closures and the anchoring
  votes that went in with them), true when its relative pose ``T_a_b`` is within 0.3 m and
  5 deg of ground truth's ``inv(T_world_a) @ T_world_b``; precision = true / all; the worst
  error of the true ones;
- recall at the first revisit: a *revisit event* is a run of keyframes (>= 3, gaps <= 3 joined)
  whose ground-truth camera is within 1 m and 30 deg of a keyframe processed earlier (another
  session's, or its own >= 30 s older); it is recalled when a true loop edge starts at one of
  its first 10 keyframes;
- ATE (cm, evo, SE3 Umeyama alignment, translation RMSE over keyframes) per session: the
  frontend's (the keyframes' ``T_odom_camera``), the server's final estimate (after the last
  keyframe, from the incrementally updated iSAM2 graph: no batch step), and the server's
  online estimate (each keyframe's ``T_map_camera`` right after its own update: what the map
  knew then);
- anchoring: when each session was anchored (its keyframes so far, seconds since its start),
  and its alignment error against ground truth relative to the session that anchored the map
  (map = that session's odom frame at its first keyframe), at its first keyframe and at its
  last (``T_map_odom`` the robot holds at the end);
- cost per keyframe (``KeyframeResult.ms``): place recognition + verification (encode + query
  + verify) and the graph update; and a scaled run that replays the cached keyframes of the
  loop-world runs of one seed as new sessions until the graph holds ``--scale`` keyframes
  (5000), reporting p50/p95 over its last 500 keyframes and the fern index's bytes per keyframe.

One core: OpenCV, numba and BLAS threads = 1.

    python bench/backend.py [--data out/bench_data] [--seeds 2001 ...] [--tune] [--only SCENARIO ...]
                            [--scale 5000] [--no-scale] [--write BENCHMARKS.md]
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import dataclasses
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import git_rev, machine, publish

from wardmap.server.backend.core import BackendConfig, BackendCore, Closure
from wardmap.shared.se3 import inverse
from wardmap.sim.runner import generate
from wardmap.sim.scenarios import build_scene
from wardmap.tools.backend_eval import (
    ClosureCheck,
    alignment_error,
    check_closure,
    recalled,
    revisit_events,
    trajectory_ate,
)
from wardmap.tools.keyframes import KeyframeCache, cache_keyframes

ROOT = Path(__file__).resolve().parents[1]
F64 = NDArray[np.float64]
NodeKey = tuple[str, str, int]
Session = tuple[str, str]
SCENARIOS = ("hospital_loop", "two_robots", "hospital_days", "ward_chairs")
EVAL_SEEDS = (2001, 2002, 2003, 2004, 2005)
TUNE_SEEDS = (1001, 1002)
ONE_ROBOT = ("hospital_days",)
"""Scenarios whose runs are sessions of one robot (robot_0), not robots of their own."""
LOOP_WORLD = ("hospital_loop", "two_robots", "hospital_days")
"""Scenarios built on the same loop world for one seed (the scaled run's sessions)."""
WINDOW = 10
LAST = 500


@dataclass(frozen=True)
class Run:
    """One robot run of a scenario and its cached keyframes."""

    name: str
    robot_id: str
    session_id: str
    cache: KeyframeCache

    @property
    def session(self) -> Session:
        return (self.robot_id, self.session_id)


@dataclass
class Step:
    """What the back-end did with one keyframe."""

    key: NodeKey
    stamp: float
    T_odom_camera: F64
    truth: F64 | None
    ms: dict[str, float]
    closures: list[Closure]
    rejected: Counter[str]
    anchored: tuple[Session, ...]
    online: F64 | None
    loops: list[tuple[NodeKey, NodeKey, F64]] = field(default_factory=list)


def progress_line(what: str) -> Callable[[int, int], None]:
    """A progress callback printing ``what: i/n`` to stderr every 100 frames."""
    def show(i: int, n: int) -> None:
        if i % 100 == 0 or i == n:
            print(f"\r  {what}: frame {i}/{n}", end="\n" if i == n else "", file=sys.stderr, flush=True)
    return show


def runs_of(data: Path, scenario: str, seed: int) -> list[Run]:
    """Generate (when missing) and track (when not cached) every run of a scenario."""
    names = [r.name for r in build_scene(scenario, seed).robots]
    out = data / f"{scenario}_s{seed}"
    folders = [out] if len(names) == 1 else [out / n for n in names]
    if not all((f / "sim.json").is_file() for f in folders):
        print(f"generating {scenario} seed {seed} ...", file=sys.stderr)
        generate(scenario, seed, out, overwrite=True)
    runs = []
    for name, folder in zip(names, folders, strict=True):
        robot_id, session_id = ("robot_0", name) if scenario in ONE_ROBOT else (name, f"s{seed}")
        cache = cache_keyframes(
            folder, data / "keyframes" / f"{scenario}_s{seed}" / name, robot_id=robot_id,
            session_id=session_id, progress=progress_line(f"keyframes of {scenario} s{seed} {name}"),
        )
        runs.append(Run(name, robot_id, session_id, cache))
    return runs


def replay(runs: list[Run], config: BackendConfig) -> tuple[BackendCore, list[Step]]:
    """Feed every run's keyframes to a fresh core in stamp order; one :class:`Step` each."""
    order = sorted((float(r.cache.stamps[k]), i, k) for i, r in enumerate(runs) for k in range(len(r.cache)))
    core = BackendCore(config)
    steps: list[Step] = []
    for _stamp, i, k in order:
        msg = runs[i].cache.message(k)
        res = core.add(msg)
        _, edges = core.graph.new_records()
        steps.append(Step(
            res.key, msg.stamp, msg.T_odom_camera, runs[i].cache.truth[k], dict(res.ms), list(res.closures),
            Counter(res.rejected), tuple(res.update.anchored), core.estimate(res.key),
            [(e.a, e.b, e.T_a_b) for e in edges if e.kind == "loop" and e.b is not None],
        ))
    return core, steps


@dataclass
class SessionScore:
    session: Session
    keyframes: int
    frontend_cm: float
    server_cm: float | None
    online_cm: float | None
    anchored_kf: int | None
    anchored_s: float | None
    start: tuple[float, float] | None
    end: tuple[float, float] | None


@dataclass
class RunScore:
    scenario: str
    seed: int
    keyframes: int
    closures: Counter[str]
    checks: list[ClosureCheck]
    events: int
    recalled: int
    sessions: list[SessionScore]
    recog_ms: list[float]
    graph_ms: list[float]
    rejected: Counter[str]

    @property
    def false(self) -> int:
        return sum(not c.true for c in self.checks)

    @property
    def precision(self) -> float | None:
        return None if not self.checks else 1.0 - self.false / len(self.checks)


def recog_ms(ms: dict[str, float]) -> float:
    return ms.get("encode", 0.0) + ms.get("query", 0.0) + ms.get("verify", 0.0)


def score(scenario: str, seed: int, core: BackendCore, steps: list[Step]) -> RunScore:
    """Score one replay against ground truth (module docstring)."""
    truth = {s.key: s.truth for s in steps if s.truth is not None}
    checks = [check_closure(a, b, T, truth[a], truth[b]) for s in steps for a, b, T in s.loops
              if a in truth and b in truth]
    posed = [s for s in steps if s.truth is not None]
    events = revisit_events([s.key for s in posed], [s.stamp for s in posed], [s.truth for s in posed])
    true_from = {c.a for c in checks if c.true}
    n_recalled = sum(recalled(e, true_from, WINDOW) for e in events)
    sessions: dict[Session, list[Step]] = {}
    for s in steps:
        sessions.setdefault((s.key[0], s.key[1]), []).append(s)
    ref = sessions[(steps[0].key[0], steps[0].key[1])]

    def odom_truth(st: Step) -> F64 | None:
        return None if st.truth is None else st.truth @ inverse(st.T_odom_camera)

    ref_est = core.estimate(ref[0].key)
    ref_map = None if ref_est is None else ref_est @ inverse(ref[0].T_odom_camera)
    ref_world = odom_truth(ref[0])
    out = []
    for session, ss in sessions.items():
        posed_ss = [s for s in ss if s.truth is not None]
        stamps = [s.stamp for s in posed_ss]
        gt = [s.truth for s in posed_ss]
        frontend = 100 * trajectory_ate(stamps, [s.T_odom_camera for s in posed_ss], gt)
        final = [core.estimate(s.key) for s in posed_ss]
        server = (100 * trajectory_ate(stamps, final, gt)) if all(T is not None for T in final) else None
        on = [(s.stamp, s.online, s.truth) for s in posed_ss if s.online is not None]
        online = 100 * trajectory_ate(*zip(*on, strict=True)) if len(on) >= 3 else None
        at = next((i for i, s in enumerate(steps) if session in s.anchored), None)
        kf = at_s = None
        if at is not None:
            kf = sum(1 for s in steps[: at + 1] if (s.key[0], s.key[1]) == session)
            at_s = steps[at].stamp - ss[0].stamp
        start = end = None
        est_first = core.estimate(ss[0].key)
        T_map_odom_end = core.T_map_odom(session)
        w_first, w_last = odom_truth(ss[0]), odom_truth(ss[-1])
        if ref_map is not None and ref_world is not None:
            if est_first is not None and w_first is not None:
                start = alignment_error(est_first @ inverse(ss[0].T_odom_camera), ref_map, w_first, ref_world)
            if T_map_odom_end is not None and w_last is not None:
                end = alignment_error(T_map_odom_end, ref_map, w_last, ref_world)
        out.append(SessionScore(session, len(ss), frontend, server, online, kf, at_s, start, end))
    closures: Counter[str] = Counter(c.kind for s in steps for c in s.closures)
    rejected: Counter[str] = Counter()
    for s in steps:
        rejected.update(s.rejected)
    return RunScore(scenario, seed, len(steps), closures, checks, len(events), n_recalled, out,
                    [recog_ms(s.ms) for s in steps], [s.ms.get("graph", 0.0) for s in steps], rejected)


@dataclass
class ScaleScore:
    keyframes: int
    sessions: int
    anchored_nodes: int
    loops: int
    recog_p50: float
    recog_p95: float
    graph_p50: float
    graph_p95: float
    index_bytes_per_kf: float
    seconds: float


def scale_run(runs: list[Run], target: int, config: BackendConfig) -> ScaleScore:
    """Replay ``runs`` (cycled) as new sessions of robot ``scale`` until ``target`` keyframes."""
    core = BackendCore(config)
    recog: list[float] = []
    graph: list[float] = []
    loops = 0
    t0 = time.perf_counter()
    rep = 0
    while len(core) < target:
        run = runs[rep % len(runs)]
        sid = f"r{rep:03d}-{run.session_id}"
        print(f"\r  scaled run: {len(core)}/{target} keyframes, session {sid}   ", end="", file=sys.stderr,
              flush=True)
        for k in range(len(run.cache)):
            if len(core) >= target:
                break
            msg = dataclasses.replace(run.cache.message(k), robot_id="scale", session_id=sid)
            res = core.add(msg)
            loops += sum(1 for c in res.closures if c.kind == "loop")
            if len(core) > target - LAST:
                recog.append(recog_ms(res.ms))
                graph.append(res.ms.get("graph", 0.0))
        rep += 1
    print(file=sys.stderr)
    anchored = sum(1 for k in core.node_keys() if core.estimate(k) is not None)
    return ScaleScore(
        len(core), rep, anchored, loops,
        float(np.percentile(recog, 50)), float(np.percentile(recog, 95)),
        float(np.percentile(graph, 50)), float(np.percentile(graph, 95)),
        core.index_nbytes() / len(core), time.perf_counter() - t0,
    )


# ------------------------------------------------------------------------------------- report


def fmt(v: float | None, spec: str = ".2f") -> str:
    return "-" if v is None else format(v, spec)


def err(e: tuple[float, float] | None) -> str:
    return "-" if e is None else f"{100 * e[0]:.2f} / {e[1]:.2f}"


def closure_rows(scores: list[RunScore]) -> list[str]:
    lines = [
        "| scenario | seed | keyframes | accepted (loop / anchor / floating) | loop edges in graph | false "
        "| precision % | worst true error cm / deg | worst false error m | revisit events | recalled "
        "| recall % |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in scores:
        trues = [c for c in s.checks if c.true]
        falses = [c for c in s.checks if not c.true]
        worst_t = (f"{100 * max(c.error_m for c in trues):.1f} / {max(c.error_deg for c in trues):.2f}"
                   if trues else "-")
        worst_f = f"{max(c.error_m for c in falses):.2f}" if falses else "-"
        recall = 100 * s.recalled / s.events if s.events else None
        lines.append(
            f"| {s.scenario} | {s.seed} | {s.keyframes} | {s.closures['loop']} / {s.closures['anchor']} / "
            f"{s.closures['floating']} | {len(s.checks)} | {s.false} "
            f"| {fmt(None if s.precision is None else 100 * s.precision, '.1f')} | {worst_t} | {worst_f} "
            f"| {s.events} | {s.recalled} | {fmt(recall, '.0f')} |"
        )
    return lines


def session_rows(scores: list[RunScore]) -> list[str]:
    lines = [
        "| scenario | seed | session | keyframes | frontend ATE cm | server ATE cm (final) "
        "| server ATE cm (online) | anchored at keyframe (s after start) | alignment at first keyframe "
        "cm / deg | alignment at last keyframe cm / deg |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in scores:
        for i, ss in enumerate(s.sessions):
            anchored = "-" if ss.anchored_kf is None else f"{ss.anchored_kf} ({ss.anchored_s:.1f})"
            lines.append(
                f"| {s.scenario} | {s.seed} | {ss.session[0]}/{ss.session[1]} | {ss.keyframes} "
                f"| {ss.frontend_cm:.2f} | {fmt(ss.server_cm)} | {fmt(ss.online_cm)} | {anchored} "
                f"| {'(map)' if i == 0 else err(ss.start)} | {err(ss.end)} |"
            )
    return lines


def summary_rows(scores: list[RunScore]) -> list[str]:
    """Mean and worst over seeds, per scenario."""
    lines = [
        "| scenario | seeds | false closures (all seeds) | precision % (all seeds) | recall % mean / worst "
        "| server ATE cm mean / worst | frontend ATE cm mean / worst | sessions anchored "
        "| alignment at first keyframe cm / deg, worst | goal |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    goals = {
        "hospital_loop": "precision 100 %, server ATE <= 1.5 cm every seed",
        "two_robots": "precision 100 %, both anchored, alignment <= 3 cm, <= 1 deg",
        "hospital_days": "precision 100 %, day 2 anchored",
        "ward_chairs": "precision 100 %",
    }
    for scenario in dict.fromkeys(s.scenario for s in scores):
        ss = [s for s in scores if s.scenario == scenario]
        checks = sum(len(s.checks) for s in ss)
        false = sum(s.false for s in ss)
        recalls = [100 * s.recalled / s.events for s in ss if s.events]
        server = [x.server_cm for s in ss for x in s.sessions if x.server_cm is not None]
        front = [x.frontend_cm for s in ss for x in s.sessions]
        n_sessions = sum(len(s.sessions) for s in ss)
        anchored = sum(x.anchored_kf is not None for s in ss for x in s.sessions)
        starts = [x.start for s in ss for x in s.sessions[1:] if x.start is not None]
        worst_start = (f"{100 * max(e[0] for e in starts):.2f} / {max(e[1] for e in starts):.2f}"
                       if starts else "-")
        precision = 100 * (1 - false / checks) if checks else None
        mean_recall, worst_recall = (float(np.mean(recalls)), min(recalls)) if recalls else (None, None)
        lines.append(
            f"| {scenario} | {len(ss)} | {false} | {fmt(precision, '.1f')} "
            f"| {fmt(mean_recall, '.0f')} / {fmt(worst_recall, '.0f')} "
            f"| {fmt(float(np.mean(server)) if server else None)} / {fmt(max(server) if server else None)} "
            f"| {np.mean(front):.2f} / {max(front):.2f} | {anchored} of {n_sessions} | {worst_start} "
            f"| {goals.get(scenario, '')} |"
        )
    return lines


def cost_rows(scores: list[RunScore], scale: ScaleScore | None) -> list[str]:
    lines = [
        "| run | keyframes in the graph | recognition + verification ms p50 / p95 "
        "| graph update ms p50 / p95 |",
        "|---|---|---|---|",
    ]
    for scenario in dict.fromkeys(s.scenario for s in scores):
        ss = [s for s in scores if s.scenario == scenario]
        rec = np.concatenate([s.recog_ms for s in ss])
        gr = np.concatenate([s.graph_ms for s in ss])
        lines.append(
            f"| {scenario} (all seeds) | up to {max(s.keyframes for s in ss)} "
            f"| {np.percentile(rec, 50):.1f} / {np.percentile(rec, 95):.1f} "
            f"| {np.percentile(gr, 50):.1f} / {np.percentile(gr, 95):.1f} |"
        )
    if scale is not None:
        lines.append(
            f"| scaled: last {LAST} of {scale.keyframes} keyframes ({scale.sessions} sessions, "
            f"{scale.anchored_nodes} on the map, {scale.loops} loop closures) | {scale.keyframes} "
            f"| {scale.recog_p50:.1f} / {scale.recog_p95:.1f} "
            f"| {scale.graph_p50:.1f} / {scale.graph_p95:.1f} |"
        )
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT / "out" / "bench_data")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(EVAL_SEEDS))
    ap.add_argument("--tune", action="store_true", help=f"the tuning seeds {TUNE_SEEDS} instead")
    ap.add_argument("--only", nargs="+", choices=SCENARIOS, help="scenarios (default: all four)")
    ap.add_argument("--scale", type=int, default=5000, help="keyframes of the scaled run (default 5000)")
    ap.add_argument("--no-scale", action="store_true", help="skip the scaled run")
    ap.add_argument("--write", type=Path, help="update this markdown file's backend section")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    seeds = list(TUNE_SEEDS) if args.tune else args.seeds
    names = args.only or list(SCENARIOS)
    config = BackendConfig()
    scores: list[RunScore] = []
    for scenario in names:
        for seed in seeds:
            runs = runs_of(args.data, scenario, seed)
            print(f"back-end over {scenario} seed {seed} ({sum(len(r.cache) for r in runs)} keyframes) ...",
                  file=sys.stderr)
            core, steps = replay(runs, config)
            scores.append(score(scenario, seed, core, steps))
            for line in closure_rows(scores[-1:])[2:] + session_rows(scores[-1:])[2:]:
                print(line, file=sys.stderr)
    scale = None
    if not args.no_scale:
        pool = [r for name in LOOP_WORLD for r in runs_of(args.data, name, seeds[0])]
        scale = scale_run(pool, args.scale, config)
    rejected: Counter[str] = Counter()
    for s in scores:
        rejected.update(s.rejected)
    command = (
        "python bench/backend.py" + (" --tune" if args.tune else f" --seeds {' '.join(map(str, seeds))}")
        + (f" --only {' '.join(names)}" if args.only else "")
        + (" --no-scale" if args.no_scale else f" --scale {args.scale}") + " --write BENCHMARKS.md"
    )
    body = "\n".join([
        "## SLAM back-end (issue 37)",
        "",
        f"Command: `{command}`  ",
        f"Machine: {machine()}; one core (OpenCV/numba/BLAS threads = 1); commit {git_rev()}.  ",
        f"World seeds {', '.join(map(str, seeds))}"
        + (" (evaluation worlds: not used for tuning)." if not set(seeds) & set(TUNE_SEEDS) else
           " (includes tuning worlds)."),
        "Keyframes: the edge frontend's messages over the simulated runs (oracle labels), fed to one "
        "`BackendCore` per scenario and seed in stamp order, no map pose anywhere. Closure truth: the "
        "loop edge's relative pose within 0.3 m and 5 deg of ground truth. Recall: revisit events "
        f"(>= 3 keyframes within 1 m and 30 deg of an earlier keyframe of another session or >= 30 s "
        f"older) with a true loop edge from one of their first {WINDOW} keyframes. ATE: evo, SE3 "
        "alignment per session, over keyframes; final = estimates after the last keyframe from the "
        "incrementally updated graph, online = each keyframe's estimate right after its own update. "
        "Alignment: relative to the session that anchored the map; definitions in "
        "`wardmap/tools/backend_eval.py` and the script's docstring.",
        "",
        "**Summary (per scenario over seeds)**",
        "",
        *summary_rows(scores),
        "",
        "**Loop closures**",
        "",
        *closure_rows(scores),
        "",
        "**Sessions: trajectory and anchoring**",
        "",
        *session_rows(scores),
        "",
        "**Cost per keyframe** (goal at 5000 keyframes: recognition + verification <= 20 ms, graph "
        "update <= 50 ms)",
        "",
        *cost_rows(scores, scale),
        "",
        (f"Fern index: {scale.index_bytes_per_kf:.0f} bytes per keyframe at {scale.keyframes} keyframes; the "
         f"scaled run took {scale.seconds:.0f} s." if scale is not None else ""),
        "Rejections by reason (all runs): "
        + ", ".join(f"{k} {v}" for k, v in rejected.most_common()) + ".",
    ])
    publish(body, args.write, "backend")
    return 0


if __name__ == "__main__":
    sys.exit(main())
