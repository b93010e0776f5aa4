"""Generate a simulated data set: render every frame of a scenario and write it.

Output (``docs/dataset.md``): one data-set folder per robot. A single-robot scenario
writes into ``out`` itself; a multi-robot scenario writes ``out/<robot>/`` for each
robot, all sharing one world frame and identical ``objects.json``. The same scenario
and seed give byte-identical files.
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

from wardmap.shared.dataset import Calibration, DatasetWriter
from wardmap.shared.errors import SimulationError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.se3 import make_transform, so3_exp, yaw_transform
from wardmap.sim.geometry import TriangleSoup
from wardmap.sim.odometry import BaseGeometry, OdometryNoise, simulate_odometry
from wardmap.sim.scenarios import RobotRun, Scene, build_scene
from wardmap.sim.sensors import SensorRig, SensorSimulator
from wardmap.sim.world import soup_of

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
CAMERA_RATE_HZ = 10.0
ODOMETRY_RATE_HZ = 50.0
SIM_EPOCH_S = 1_700_000_000.0
FORMAT_VERSION = 1


@dataclass(frozen=True)
class RobotSummary:
    """What was written for one robot."""

    name: str
    path: Path
    frames: int
    duration_s: float
    length_m: float


def base_pose(run: RobotRun, t: F64) -> F64:
    """Ground-truth base poses ``T_world_base`` (N, 4, 4) at times ``t`` (N,) seconds.

    Planar motion plus a small deterministic rocking (floor joints, tyre compliance):
    pitch and roll of a few tenths of a degree as functions of the distance travelled.
    """
    x, y, yaw, s = run.track.at(t)
    out = np.empty((len(t), 4, 4))
    for i in range(len(t)):
        pitch = np.radians(0.25) * np.sin(2 * np.pi * s[i] / 0.61) + np.radians(0.1) * np.sin(
            2 * np.pi * s[i] / 0.23
        )
        roll = np.radians(0.2) * np.sin(2 * np.pi * s[i] / 0.83 + 1.0)
        rock = make_transform(so3_exp([roll, pitch, 0.0]), [0.0, 0.0, 0.0])
        out[i] = yaw_transform(float(x[i]), float(y[i]), float(yaw[i])) @ rock
    return out


def calibration_of(rig: SensorRig, geometry: BaseGeometry) -> Calibration:
    return Calibration(
        rgb=rig.rgb,
        depth_scale=5000.0,
        thermal=rig.thermal,
        T_rgb_thermal=rig.T_rgb_thermal,
        thermal_scale=100.0,
        T_base_rgb=rig.T_base_rgb,
        wheel_radius_m=geometry.wheel_radius_m,
        wheel_base_m=geometry.wheel_base_m,
        ticks_per_mm=geometry.ticks_per_mm,
    )


def objects_document(scene: Scene, stamps: F64, kg: KnowledgeGraph) -> dict[str, object]:
    """``objects.json``: every instance with class, mobility, pose, size; moving ones per frame."""
    objects: list[dict[str, object]] = []
    for o in scene.world.objects:
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
            "name": scene.world.name,
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
    geometry = BaseGeometry()
    kg = KnowledgeGraph.load()
    sensors = SensorSimulator(scene.world.static, scene.world.bank.stack(), rig)
    out = Path(out)
    multi = len(scene.robots) > 1
    summaries = []
    for r_index, run in enumerate(scene.robots):
        root = out / run.name if multi else out
        n_total = int(np.floor(run.track.duration * CAMERA_RATE_HZ)) + 1
        n = min(n_total, frames) if frames is not None else n_total
        t_cam = run.track.t[0] + np.arange(n) / CAMERA_RATE_HZ
        stamps = np.round(SIM_EPOCH_S + t_cam, 6)
        T_world_base = base_pose(run, t_cam)
        rng = np.random.default_rng([seed, r_index, 1])
        started = time.perf_counter()
        with DatasetWriter(root, calibration_of(rig, geometry), overwrite=overwrite) as writer:
            for i in range(n):
                t = float(t_cam[i])
                dyn = TriangleSoup.concat([soup_of(*a.at(t), a.id, scene.world.bank) for a in scene.actors])
                T_world_rgb = T_world_base[i] @ rig.T_base_rgb
                f = sensors.capture(T_world_rgb, dyn, scene.light(t), rng)
                writer.write_frame(
                    float(stamps[i]),
                    f.rgb,
                    f.depth_m,
                    thermal_k=f.thermal_k,
                    labels=f.labels,
                    T_world_camera=T_world_rgb,
                )
                if progress is not None:
                    progress(run.name, i + 1, n)
            t_odo = np.arange(run.track.t[0], t_cam[-1] + 1e-9, 1.0 / ODOMETRY_RATE_HZ)
            odo = simulate_odometry(
                np.round(SIM_EPOCH_S + t_odo, 6),
                base_pose(run, t_odo),
                geometry,
                OdometryNoise(),
                np.random.default_rng([seed, r_index, 2]),
            )
            writer.write_odometry(odo.stamps, odo.T_odom_base)
            writer.write_encoders(odo.encoders)
            writer.write_objects(objects_document(scene, stamps, kg))
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
