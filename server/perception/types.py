"""Data types that flow from perception into association (paper 000 Eq. 1).

Frames follow docs/ARCHITECTURE.md: ``T_a_b`` maps points in frame b to frame a. A
keyframe's camera frame is x right, y down, z forward; an object's frame has x forward,
z up (gravity-aligned), origin at the centre of its bounding box, like the simulator's
``objects.json``. ``world`` is the frame the keyframe poses are given in (a robot
session's odom frame on the live server, the data set's ground-truth frame offline).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

__all__ = ["CLASS_SIZE_M", "Instance", "ObjectMeasurement"]

CLASS_SIZE_M: tuple[tuple[str, float, float], ...] = (
    ("bed", 2.3, 1.1), ("door", 1.3, 2.3), ("cabinet", 1.3, 2.1), ("desk", 1.8, 0.9),
    ("cart", 1.2, 1.2), ("wheelchair", 1.2, 1.1), ("sink", 0.9, 1.1), ("wall_monitor", 1.1, 0.8),
    ("chair", 0.6, 1.1), ("iv_pole", 0.7, 2.2),
)
"""``(class, largest horizontal extent, height)`` of an object of the class, metres: the
defaults of the association's ``HdpConfig.class_size_m`` and of the measurement's
``MeasureConfig.max_width_m`` (one table, so the two cannot drift apart)."""


@dataclass(frozen=True, eq=False)
class Instance:
    """One object instance found in one image.

    Attributes:
        category: knowledge-graph class name (e.g. ``"door"``).
        confidence: score in [0, 1] (1 for ground-truth instances).
        mask: (H, W) bool, the instance's pixels in the colour image.
        box_xyxy: (4,) float64 ``x1, y1, x2, y2`` in pixels (``shared/detection.py``
            convention: a box covering the last column ends at x = W).
        gt_instance: the simulator's instance id most of the mask covers, when the
            data set has ground-truth labels; ``None`` otherwise.
    """

    category: str
    confidence: float
    mask: NDArray[np.bool_]
    box_xyxy: NDArray[np.float64]
    gt_instance: int | None = None


@dataclass(frozen=True, eq=False)
class ObjectMeasurement:
    """A 3D measurement of one instance in one keyframe (paper 000 Eq. 1: class, pose, size).

    Attributes:
        keyframe: keyframe key, ``"<robot>/<session>/<seq>"`` on the server or
            ``"<dataset name>/<stamp>"`` offline.
        stamp: keyframe time, seconds.
        category: knowledge-graph class name.
        confidence: in [0, 1].
        box_xyxy: (4,) float64 pixel box in the keyframe's colour image.
        mask: (H, W) bool instance mask in the colour image.
        points_camera: (N, 3) float32 inlier 3D points of the instance, camera frame, metres.
        T_camera_object: (4, 4) float64 object pose in the camera frame.
        T_world_camera: (4, 4) float64 the keyframe's camera pose in ``world``.
        T_world_object: (4, 4) float64 ``T_world_camera @ T_camera_object``; z up.
        size: (3,) float64 extent along the object's x, y, z, metres.
        color_hist: (K,) float32 L1-normalised colour histogram inside the mask.
        descriptors: (M, 32) uint8 ORB descriptors of keypoints inside the mask (M may be 0).
        gt_instance: ground-truth instance id under the mask, when known.
    """

    keyframe: str
    stamp: float
    category: str
    confidence: float
    box_xyxy: NDArray[np.float64]
    mask: NDArray[np.bool_]
    points_camera: NDArray[np.float32]
    T_camera_object: NDArray[np.float64]
    T_world_camera: NDArray[np.float64]
    T_world_object: NDArray[np.float64]
    size: NDArray[np.float64]
    color_hist: NDArray[np.float32]
    descriptors: NDArray[np.uint8] = field(default_factory=lambda: np.zeros((0, 32), np.uint8))
    gt_instance: int | None = None
