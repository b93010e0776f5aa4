"""Render one simulated robot frame by frame, without writing files.

:class:`LiveRun` reads like :class:`wardmap.shared.dataset.DatasetReader` (``calibration``,
``stamps``, ``len``, :meth:`~LiveRun.frame`, :meth:`~LiveRun.odometry`,
:meth:`~LiveRun.groundtruth`, :meth:`~LiveRun.objects`), so the tracking frontend, the
label sources and the edge agent run on it unchanged (``wardmap edge --source
sim:SCENARIO[:SEED[:ROBOT]]``). :func:`wardmap.sim.runner.generate` writes the same
frames to disk: frame ``i`` of a :class:`LiveRun` is byte-identical to frame ``i`` of the
folder ``wardmap sim`` writes for the same scenario, seed and robot.

Sensor noise comes from one random stream per robot, consumed frame after frame, so
frames are cheapest read in order; reading an earlier frame again re-renders from the
first one.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from wardmap.shared.dataset import Calibration, Frame
from wardmap.shared.errors import SimulationError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.se3 import make_transform, so3_exp, yaw_transform
from wardmap.sim.geometry import TriangleSoup
from wardmap.sim.odometry import BaseGeometry, OdometryNoise, simulate_odometry
from wardmap.sim.scenarios import SCENARIOS, Scene, build_scene
from wardmap.sim.sensors import SensorRig, SensorSimulator
from wardmap.sim.world import soup_of

F64 = NDArray[np.float64]
CAMERA_RATE_HZ: Final = 10.0
ODOMETRY_RATE_HZ: Final = 50.0
SIM_EPOCH_S: Final = 1_700_000_000.0
SOURCE_PREFIX: Final = "sim:"
_SPEC = re.compile(r"^sim:(?P<scenario>[a-z0-9_]+)(?::(?P<seed>[0-9]+)(?::(?P<robot>[A-Za-z0-9_.-]+))?)?$")


@dataclass(frozen=True)
class SimSource:
    """A parsed ``sim:SCENARIO[:SEED[:ROBOT]]`` source (seed 0 and the first robot by default)."""

    scenario: str
    seed: int = 0
    robot: str | None = None

    @staticmethod
    def parse(spec: str) -> SimSource:
        """Parse ``sim:SCENARIO[:SEED[:ROBOT]]``.

        Raises:
            SimulationError: malformed spec or unknown scenario (the message lists them).
        """
        m = _SPEC.match(spec.strip())
        if m is None:
            raise SimulationError(f"bad simulated source {spec!r}; expected sim:SCENARIO[:SEED[:ROBOT]], "
                                  "e.g. sim:aisle_slow_1 or sim:two_robots:0:robot_1")
        if m["scenario"] not in SCENARIOS:
            raise SimulationError(f"unknown scenario {m['scenario']!r} in {spec!r}; known: "
                                  + ", ".join(sorted(SCENARIOS)))
        return SimSource(m["scenario"], int(m["seed"] or 0), m["robot"])


def is_sim_source(spec: str | Path) -> bool:
    """True when ``spec`` names a simulated source rather than a folder."""
    return isinstance(spec, str) and spec.startswith(SOURCE_PREFIX)


def base_pose(run: Any, t: F64) -> F64:
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
    """The data-set calibration of the simulated rig (depth 5000 per metre, thermal 0.01 K)."""
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
        rgb_readout_s=rig.rgb_readout_s,  # 0: the renderer exposes every row at once
    )


class LiveRun:
    """One robot of a scenario, rendered on demand (see the module docstring).

    Attributes:
        root: a display name, ``sim:SCENARIO:SEED:ROBOT`` (no folder exists).
        calibration: the rig's calibration.
        stamps: (N,) colour stamps in seconds.
        robot: the robot's name in the scenario.
    """

    def __init__(
        self,
        scenario: str,
        seed: int = 0,
        robot: str | None = None,
        *,
        frames: int | None = None,
        rig: SensorRig | None = None,
        scene: Scene | None = None,
        sensors: SensorSimulator | None = None,
    ) -> None:
        """Build the scene (or reuse ``scene``/``sensors`` of the same scenario and seed; ``sensors``
        must render this run's world, :meth:`Scene.world_of`).

        Raises:
            SimulationError: unknown scenario or robot, bad frame count.
        """
        if frames is not None and frames <= 0:
            raise SimulationError(f"frames must be positive, got {frames}")
        self.scene = scene if scene is not None else build_scene(scenario, seed)
        names = [r.name for r in self.scene.robots]
        if robot is None:
            robot = names[0]
        if robot not in names:
            raise SimulationError(
                f"scenario {scenario!r} has no robot {robot!r}; its robots: {', '.join(names)}"
            )
        self.robot = robot
        self.robot_index = names.index(robot)
        self.run = self.scene.robots[self.robot_index]
        self.rig = rig or SensorRig()
        self.geometry = BaseGeometry()
        self.calibration = calibration_of(self.rig, self.geometry)
        self.root = Path(f"sim:{scenario}:{seed}:{robot}")
        self._sensors = sensors
        n_total = int(np.floor(self.run.track.duration * CAMERA_RATE_HZ)) + 1
        n = min(n_total, frames) if frames is not None else n_total
        self.t_cam: F64 = self.run.track.t[0] + np.arange(n) / CAMERA_RATE_HZ
        self.stamps: F64 = np.round(SIM_EPOCH_S + self.t_cam, 6)
        self.T_world_base: F64 = base_pose(self.run, self.t_cam)
        self._seed = seed
        self._rng = self._new_rng()
        self._next = 0
        self._odometry: Any = None

    def _new_rng(self) -> np.random.Generator:
        return np.random.default_rng([self._seed, self.robot_index, 1])

    @property
    def sensors(self) -> SensorSimulator:
        """The renderer (built on first use: it holds the world's texture atlas)."""
        if self._sensors is None:
            world = self.scene.world_of(self.run)
            self._sensors = SensorSimulator(world.static, world.bank.stack(), self.rig)
        return self._sensors

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def has_thermal(self) -> bool:
        """Always True: the rig has a thermal camera."""
        return True

    @property
    def has_labels(self) -> bool:
        """Always True: every frame has instance labels."""
        return True

    @property
    def has_groundtruth(self) -> bool:
        """Always True: see :meth:`groundtruth`."""
        return True

    def __repr__(self) -> str:
        return f"LiveRun({str(self.root)!r}, {len(self)} frames)"

    def frame(self, i: int) -> Frame:
        """Render frame ``i`` (cheap in order; see the module docstring).

        Raises:
            IndexError: ``i`` out of range.
        """
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for {n} frames")
        i %= n
        if i < self._next:
            self._rng, self._next = self._new_rng(), 0
        while True:
            f = self._capture(self._next)
            self._next += 1
            if self._next > i:
                return f

    def _capture(self, i: int) -> Frame:
        t = float(self.t_cam[i])
        scene = self.scene
        bank = scene.world_of(self.run).bank
        dyn = TriangleSoup.concat([soup_of(*a.at(t), a.id, bank) for a in scene.actors])
        T_world_rgb = self.T_world_base[i] @ self.rig.T_base_rgb
        band_poses = None
        if self.rig.rgb_readout_s > 0.0:  # rolling shutter: each band of rows at its own instant
            band_t = np.array([t + dt for _, _, dt in self.rig.readout_bands()])
            band_poses = list(base_pose(self.run, band_t) @ self.rig.T_base_rgb)
        f = self.sensors.capture(T_world_rgb, dyn, scene.light(t), self._rng, band_poses=band_poses)
        stamp = float(self.stamps[i])
        return Frame(
            index=i,
            stamp=stamp,
            rgb=f.rgb,
            depth_m=f.depth_m,
            thermal_k=f.thermal_k,
            labels=f.labels,
            T_world_camera=T_world_rgb,
            depth_stamp=stamp,
            thermal_stamp=stamp,
        )

    def odometry(self) -> tuple[F64, F64]:
        """Wheel odometry ``(stamps (M,), T_odom_base (M, 4, 4))`` at 50 Hz up to the last frame."""
        return self.odometry_run()[:2]

    def odometry_run(self) -> tuple[F64, F64, F64]:
        """``(stamps, T_odom_base, encoders)`` of :func:`simulate_odometry` (computed once)."""
        if self._odometry is None:
            t_odo = np.arange(self.run.track.t[0], self.t_cam[-1] + 1e-9, 1.0 / ODOMETRY_RATE_HZ)
            odo = simulate_odometry(
                np.round(SIM_EPOCH_S + t_odo, 6),
                base_pose(self.run, t_odo),
                self.geometry,
                OdometryNoise(),
                np.random.default_rng([self._seed, self.robot_index, 2]),
            )
            self._odometry = (odo.stamps, odo.T_odom_base, odo.encoders)
        stamps, T, enc = self._odometry
        return stamps, T, enc

    def T_world_odom(self) -> F64:
        """(4, 4) the odometry frame in the world: the base at the first stamp, planar (z = 0, no tilt).

        What an operator knows when the robot starts at a known map pose (its dock); give it to
        ``wardmap edge --map-pose X,Y,YAW_DEG``.
        """
        x, y, yaw, _ = self.run.track.at(self.run.track.t[:1])
        return yaw_transform(float(x[0]), float(y[0]), float(yaw[0]))

    def groundtruth(self) -> tuple[F64, F64]:
        """Ground-truth ``(stamps (N,), T_world_camera (N, 4, 4))`` of the colour camera."""
        return self.stamps, self.T_world_base @ self.rig.T_base_rgb

    def objects(self) -> dict[str, Any]:
        """The ``objects.json`` document of the scene (docs/dataset.md)."""
        from wardmap.sim.runner import objects_document

        return objects_document(self.scene, self.stamps, KnowledgeGraph.load(), self.scene.world_of(self.run))
