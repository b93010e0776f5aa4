"""Generate a simulated data set: render every frame of a scenario and write it.

Output (``docs/dataset.md``): one data-set folder per robot. A single-robot scenario
writes into ``out`` itself; a multi-robot scenario writes ``out/<robot>/`` for each
robot run, all sharing one world frame; each ``objects.json`` describes its run's world
(identical unless the scenario moves objects between runs, as ``hospital_days`` does
between its two days). The same scenario and seed give byte-identical files.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from wardmap.shared.dataset import DatasetWriter
from wardmap.shared.errors import SimulationError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.sim.live import (
    CAMERA_RATE_HZ,
    ODOMETRY_RATE_HZ,
    SIM_EPOCH_S,
    LiveRun,
    base_pose,
    calibration_of,
)
from wardmap.sim.scenarios import Scene, build_scene
from wardmap.sim.sensors import SensorRig, SensorSimulator
from wardmap.sim.world import World

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
FORMAT_VERSION = 1
__all__ = [
    "CAMERA_RATE_HZ", "ODOMETRY_RATE_HZ", "SIM_EPOCH_S", "RobotSummary", "base_pose", "calibration_of",
    "generate", "objects_document",
]


@dataclass(frozen=True)
class RobotSummary:
    """What was written for one robot."""

    name: str
    path: Path
    frames: int
    duration_s: float
    length_m: float


def objects_document(
    scene: Scene, stamps: F64, kg: KnowledgeGraph, world: World | None = None
) -> dict[str, object]:
    """``objects.json``: every instance with class, mobility, pose, size; moving ones per frame.

    ``world``: the run's world (:meth:`Scene.world_of`); None: the scene's.
    """
    world = scene.world if world is None else world
    objects: list[dict[str, object]] = []
    for o in world.objects:
        objects.append(
            {
                "id": o.id,
                "class": o.cls,
                "mobility": str(kg.mobility(o.cls)),
                "moves": False,
                "T_world_object": np.round(o.T_world_object, 6).tolist(),
                "size": np.round(o.size, 4).tolist(),
                "note": o.note,
            }
        )
    for a in scene.actors:
        T0, size = a.object_pose(0.0)
        traj = []
        for st in stamps:
            T, _ = a.object_pose(float(st - SIM_EPOCH_S))
            traj.append({"stamp": round(float(st), 6), "T_world_object": np.round(T, 6).tolist()})
        entry: dict[str, object] = {
            "id": a.id,
            "class": a.cls,
            "mobility": str(kg.mobility(a.cls)),
            "moves": True,
            "T_world_object": np.round(T0, 6).tolist(),
            "size": np.round(size, 4).tolist(),
            "trajectory": traj,
        }
        role = getattr(a, "role", None)
        if role:
            entry["role"] = role
        objects.append(entry)
    objects.sort(key=lambda d: int(d["id"]))  # type: ignore[call-overload]
    return {
        "format_version": FORMAT_VERSION,
        "world": {
            "name": world.name,
            "scenario": scene.name,
            "seed": scene.seed,
            "frame": "world",
            "description": scene.description,
        },
        "classes": {c.name: str(c.mobility) for c in kg.classes},
        "objects": objects,
    }


def generate(
    scenario: str,
    seed: int,
    out: str | Path,
    *,
    frames: int | None = None,
    overwrite: bool = False,
    progress: Callable[[str, int, int], None] | None = None,
    rig: SensorRig | None = None,
) -> list[RobotSummary]:
    """Render scenario ``scenario`` with ``seed`` into ``out``; returns one summary per robot.

    Args:
        frames: write at most this many camera frames per robot (None: the whole path).
        overwrite: allow writing into a non-empty folder.
        progress: called as ``progress(robot, frame_index, total_frames)``.

    Raises:
        SimulationError: unknown scenario, bad frame count.
        DatasetError: the output folder cannot be written.
    """
    if frames is not None and frames <= 0:
        raise SimulationError(f"--frames must be positive, got {frames}")
    scene = build_scene(scenario, seed)
    rig = rig or SensorRig()
    kg = KnowledgeGraph.load()
    sensors: dict[int, SensorSimulator] = {}  # id(world) -> its renderer (one per distinct world)
    out = Path(out)
    multi = len(scene.robots) > 1
    summaries = []
    for run in scene.robots:
        world = scene.world_of(run)
        if id(world) not in sensors:
            sensors[id(world)] = SensorSimulator(world.static, world.bank.stack(), rig)
        root = out / run.name if multi else out
        live = LiveRun(
            scenario, seed, run.name, frames=frames, rig=rig, scene=scene, sensors=sensors[id(world)]
        )
        n = len(live)
        started = time.perf_counter()
        with DatasetWriter(root, live.calibration, overwrite=overwrite) as writer:
            for i in range(n):
                f = live.frame(i)
                writer.write_frame(
                    f.stamp, f.rgb, f.depth_m, thermal_k=f.thermal_k, labels=f.labels,
                    T_world_camera=f.T_world_camera,
                )
                if progress is not None:
                    progress(run.name, i + 1, n)
            odo_stamps, T_odom_base, encoders = live.odometry_run()
            writer.write_odometry(odo_stamps, T_odom_base)
            writer.write_encoders(encoders)
            writer.write_objects(objects_document(scene, live.stamps, kg, world))
        t_cam = live.t_cam
        (root / "sim.json").write_text(
            json.dumps(
                {
                    "scenario": scenario,
                    "seed": seed,
                    "robot": run.name,
                    "frames": n,
                    "camera_rate_hz": CAMERA_RATE_HZ,
                    "odometry_rate_hz": ODOMETRY_RATE_HZ,
                    "format_version": FORMAT_VERSION,
                    "description": scene.description,
                },
                indent=2,
                sort_keys=True,
            )
            + "\n"
        )
        _, _, _, s = run.track.at(t_cam)
        summaries.append(RobotSummary(run.name, root, n, float(t_cam[-1] - t_cam[0]), float(s[-1] - s[0])))
        log.info("%s: %d frames in %.1f s", run.name, n, time.perf_counter() - started)
    return summaries
