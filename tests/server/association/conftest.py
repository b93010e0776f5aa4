"""Synthetic object measurements for the association tests (known ground truth, no images)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from wardmap.server.association.geometry import project_box
from wardmap.server.perception.types import ObjectMeasurement
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.se3 import inverse, make_transform

CAMERA = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
CHAIR_SIZE = np.array([0.46, 0.46, 0.93])


def camera_looking_along_y(x: float, y: float = 0.0, z: float = 0.8) -> np.ndarray:
    """T_world_camera (4, 4) of a camera at (x, y, z) looking along world +y (x right, z up in world)."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # columns: cam x, y, z in world
    return make_transform(R, [x, y, z])


def object_pose(x: float, y: float, z: float = 0.465, yaw: float = 0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return make_transform([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], [x, y, z])


MeasurementFactory = Callable[..., ObjectMeasurement]


@pytest.fixture
def make_measurement() -> MeasurementFactory:
    """Factory: a measurement of a box seen from a camera, with optional position noise."""

    def make(
        T_world_object: np.ndarray,
        T_world_camera: np.ndarray,
        *,
        category: str = "chair",
        size: np.ndarray = CHAIR_SIZE,
        gt: int | None = None,
        keyframe: str = "kf",
        stamp: float = 0.0,
        offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> ObjectMeasurement:
        T_wo = T_world_object.copy()
        T_wo[:3, 3] += np.asarray(offset)
        box = project_box(T_wo, size, T_world_camera, CAMERA)
        if box is None:
            raise ValueError("object not in view")
        return ObjectMeasurement(
            keyframe=keyframe,
            stamp=stamp,
            category=category,
            confidence=1.0,
            box_xyxy=box,
            mask=np.zeros((0, 0), dtype=bool),
            points_camera=np.zeros((0, 3), dtype=np.float32),
            T_camera_object=inverse(T_world_camera) @ T_wo,
            T_world_camera=T_world_camera,
            T_world_object=T_wo,
            size=np.asarray(size, dtype=np.float64),
            color_hist=np.full(8, 1 / 8, dtype=np.float32),
            gt_instance=gt,
        )

    return make
