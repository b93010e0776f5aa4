"""One keyframe through server perception: images -> instances -> 3D object measurements.

:func:`measure_keyframe` is the one order of steps that the server's mapping stage,
``wardmap map`` (``tools/offline_map.py``) and ``bench/perception.py`` run:

1. find instances: run the segmenter (``models.py``), or take the instances given;
2. split them into one instance per object (``instances.split_instances``: the
   segmentation network's instances only);
3. leave out the knowledge graph's ``moving`` classes (people; paper 001 Sec. 3.2: never
   part of the map);
4. leave out misplaced instances of floor-standing classes (``floor.drop_misplaced``:
   floating, pieces of a taller surface, flat on the floor), where the floor is known;
5. attach the simulator's instance ids under each mask, when a label image is given (for
   scoring; nothing downstream decides on them);
6. measure each instance in 3D (``measure.measure_instances_report``, paper 000 Eq. 1).

Ground-truth instances (``source="oracle"``: the simulator's label images) skip steps 2
and 4: each is one whole object, and it is where it is.

Steps 3-5 decide on each instance alone (its class, mask and depth, the camera pose and
the floor: no check looks at another instance or draws from a shared random sequence), and
step 6 measures each instance alone with a fixed seed. So their order changes neither
which instances are measured nor the measurements, only what a count could be booked as
when one instance fails two checks (a ``moving`` class also listed in a floor check's table
is counted as moving).

For keyframes on the wire (``shared.wire.KeyframeMsg``): :func:`decode_keyframe_images`,
:func:`keyframe_camera`, :func:`keyframe_map_pose`, :func:`keyframe_floor_z`, and
:func:`measure_keyframe_msg`, which ties them to :func:`measure_keyframe`.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.server.decoded import KeyframeImages, decode_images
from wardmap.server.perception.config import PerceptionConfig, measure_config_for
from wardmap.server.perception.floor import LeftOut, drop_misplaced
from wardmap.server.perception.instances import attach_gt_instances, split_instances
from wardmap.server.perception.measure import Skip, SkipKind, measure_instances_report
from wardmap.server.perception.types import Instance, ObjectMeasurement
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import GeometryError, WireError
from wardmap.shared.se3 import check_transform
from wardmap.shared.wire import KeyframeMsg

__all__ = [
    "ORACLE",
    "FindInstances",
    "KeyframePerception",
    "decode_keyframe_images",
    "keyframe_camera",
    "keyframe_floor_z",
    "keyframe_map_pose",
    "measure_keyframe",
    "measure_keyframe_msg",
]

log = logging.getLogger(__name__)

U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

ORACLE: Final = "oracle"
"""The ``source`` of ground-truth instances (the simulator's label images)."""

FindInstances = Callable[[U8, F32], Sequence[Instance]]
"""What finds instances in a uint8 (H, W, 3) BGR image with float32 (H, W) depth in metres:
a :class:`~wardmap.server.perception.models.Segmenter`, or any callable like it."""


@dataclass(frozen=True, eq=False)
class KeyframePerception:
    """What :func:`measure_keyframe` made of one keyframe, and what each step left out.

    Attributes:
        measurements: the 3D measurements, in the order of the instances they come from.
        found: instances found (after the split) or given.
        moving: instances of ``moving`` classes left out.
        left_out: instances the floor checks left out, by check (``floor.LeftOut``: floating,
            wall pieces, floor pieces; all 0 where the floor is unknown or for ground truth).
        skipped: instances measurement could not measure, each with its index among the
            instances measured, kind and reason (``measure.Skip``).
    """

    measurements: list[ObjectMeasurement]
    found: int
    moving: int
    left_out: LeftOut
    skipped: list[Skip]

    def skipped_by_kind(self) -> Counter[SkipKind]:
        """How many instances were not measured, by kind (``measure.SKIP_KINDS``)."""
        return Counter(skip.kind for skip in self.skipped)


def measure_keyframe(
    bgr: U8,
    depth_m: F32,
    camera: PinholeCamera,
    T_world_camera: ArrayLike,
    *,
    keyframe: str,
    stamp: float,
    floor_z_m: float | None,
    instances: FindInstances | Sequence[Instance],
    config: PerceptionConfig,
    moving: Collection[str],
    source: str | None = None,
    instance_ids: NDArray[np.uint16] | None = None,
) -> KeyframePerception:
    """Instances of one keyframe, filtered and measured in 3D (the module's steps, in order).

    Args:
        bgr: uint8 (H, W, 3) colour image, BGR order (OpenCV).
        depth_m: float32 (H, W) depth along the camera z axis, metres, registered to the
            colour camera; 0 = no measurement.
        camera: the colour camera (its width and height are the images').
        T_world_camera: (4, 4) float64 camera pose in ``world`` (the map frame on the
            server, the data set's ground-truth frame offline); world z is up.
        keyframe: the key stored in each measurement (``<robot>/<session>/<seq>`` on the
            server, ``<dataset>/<stamp>`` offline).
        stamp: keyframe time, seconds.
        floor_z_m: height of the floor along world z, metres (``floor.floor_under``,
            :func:`keyframe_floor_z`); None when unknown (a hand-held camera): no floor check.
        instances: the segmenter to run on ``bgr`` and ``depth_m``, or the instances already
            found in them (by the segmenter of ``source``, or ground truth).
        config: the perception settings (split, floor checks, measurement).
        moving: names of the classes left out as moving (``KnowledgeGraph.moving_classes()``).
        source: what found the instances: a segmenter spec (``model``, ``model:PATH``,
            ``yolox:PATH``; only ``model`` specs are split, and a ``yolox:`` detector's
            measurement uses ``detector_cluster_gap_m``) or :data:`ORACLE` for ground truth
            (neither split nor checked against the floor). None: ``config.segmenter``.
        instance_ids: uint16 (H, W) simulator instance ids of the image (its label image),
            to set each instance's ``gt_instance``; None leaves them as found.

    Returns:
        The measurements and the counts of each step (:class:`KeyframePerception`).

    Raises:
        GeometryError: the images or the pose do not have the shapes above.
    """
    image, depth = _check_images(bgr, depth_m, camera)
    T = check_transform(T_world_camera, "T_world_camera")
    spec = config.segmenter if source is None else source
    truth = spec == ORACLE
    given = list(instances(image, depth) if callable(instances) else instances)  # 1. find
    if not truth:
        given = split_instances(given, depth, camera, config, spec)  # 2. split
    kept = [inst for inst in given if inst.category not in moving]  # 3. moving classes
    n_moving = len(given) - len(kept)
    left_out = LeftOut(0, 0, 0)
    if not truth:  # 4. floor checks
        kept, left_out = drop_misplaced(kept, depth, camera, config, T, floor_z_m)
        if any(left_out):
            log.debug("keyframe %s: %d instance(s) float above the floor, %d lie on a taller surface, "
                      "%d lie flat on the floor; left out", keyframe, *left_out)
    if instance_ids is not None:  # 5. ground-truth ids
        kept = attach_gt_instances(kept, instance_ids)
    report = measure_instances_report(  # 6. measurement
        kept, bgr=image, depth_m=depth, camera=camera, T_world_camera=T, keyframe=keyframe, stamp=stamp,
        config=measure_config_for(config, spec),
    )
    return KeyframePerception(report.measurements, len(given), n_moving, left_out, report.skipped)


def _check_images(bgr: ArrayLike, depth_m: ArrayLike, camera: PinholeCamera) -> tuple[U8, F32]:
    image = np.asarray(bgr)
    depth = np.asarray(depth_m)
    shape = (camera.height, camera.width)
    if image.dtype != np.uint8 or image.shape != (*shape, 3):
        raise GeometryError(f"measure_keyframe: expected a uint8 {(*shape, 3)} BGR image, "
                            f"got {image.dtype} {image.shape}")
    if depth.shape != shape:
        raise GeometryError(f"measure_keyframe: expected depth {shape}, got {depth.shape}")
    return image, depth


# ---------------------------------------------------------------------------- keyframes on the wire


def keyframe_camera(msg: KeyframeMsg) -> PinholeCamera:
    """The colour camera of a keyframe (its intrinsics; ``calib_ref`` is not resolvable yet).

    Raises:
        WireError: the keyframe names its calibration by ``calib_ref``.
    """
    i = msg.intrinsics
    if i is None:
        raise WireError("calib_ref", "keyframes with calib_ref are not supported by the mapping stage yet")
    return PinholeCamera(i.width, i.height, i.fx, i.fy, i.cx, i.cy, tuple(i.distortion))  # type: ignore[arg-type]


def decode_keyframe_images(msg: KeyframeMsg,
                           images: KeyframeImages | None = None) -> tuple[U8, F32, PinholeCamera]:
    """``(bgr (H, W, 3) uint8, depth (H, W) float32 metres at colour size, camera)``, from
    ``images`` (``msg``'s rasters already decoded) or decoded from ``msg`` when None.

    Depth sent at 1/s resolution is upsampled by repetition: colour pixel (y, x) takes depth
    pixel (y // s, x // s) (docs/wire.md, ``depth``).

    Raises:
        WireError: the colour image does not decode at the intrinsics' size, or the depth
            does not decode; ``calib_ref`` instead of intrinsics.
    """
    camera = keyframe_camera(msg)
    if images is None:
        images = decode_images(msg)
    bgr, depth = images.bgr, images.depth_m
    if bgr.shape[:2] != (camera.height, camera.width):
        raise WireError("rgb_jpeg", "cannot decode the colour image at the intrinsics' size")
    s = camera.height // depth.shape[0]
    if s > 1:
        depth = np.repeat(np.repeat(depth, s, axis=0), s, axis=1)
    return np.ascontiguousarray(bgr, np.uint8), np.ascontiguousarray(depth, np.float32), camera


def keyframe_map_pose(msg: KeyframeMsg) -> F64:
    """``T_map_camera`` (4, 4) of a keyframe: ``T_map_odom @ T_odom_camera``, with the identity
    for ``T_map_odom`` when the session is not on the map (its odom frame stands in)."""
    T_map_odom = msg.T_map_odom if msg.T_map_odom is not None else np.eye(4)
    return np.asarray(T_map_odom @ msg.T_odom_camera, np.float64)


def keyframe_floor_z(msg: KeyframeMsg) -> float | None:
    """Height (m) of the floor along z in the frame of :func:`keyframe_map_pose`: that of the
    robot base, whose frame sits on the floor (``T_map_odom @ T_odom_base``); None for
    keyframes without a base (a hand-held camera).

    The base pose is the wheel odometry's, not ``T_odom_camera`` through the base-to-camera
    calibration (``floor.floor_under``, for data sets without odometry): on a robot the two
    differ by the tracker's drift against the wheels.
    """
    if msg.T_odom_base is None:
        return None
    T_map_odom = msg.T_map_odom if msg.T_map_odom is not None else np.eye(4)
    return float((T_map_odom @ msg.T_odom_base)[2, 3])


def measure_keyframe_msg(
    msg: KeyframeMsg,
    key: str,
    *,
    segmenter: FindInstances,
    config: PerceptionConfig,
    moving: Collection[str],
    images: KeyframeImages | None = None,
) -> KeyframePerception:
    """:func:`measure_keyframe` of a decoded keyframe message, in the map frame
    (:func:`keyframe_map_pose`, floor from :func:`keyframe_floor_z`), with ``config.segmenter``
    as the source of ``segmenter``'s instances; ``key`` goes into each measurement; ``images``:
    its rasters already decoded, or None (decoded here).

    Raises:
        WireError: images that do not decode, or no intrinsics (:func:`decode_keyframe_images`).
        GeometryError: images or pose of the wrong shape.
    """
    bgr, depth, camera = decode_keyframe_images(msg, images)
    return measure_keyframe(bgr, depth, camera, keyframe_map_pose(msg), keyframe=key, stamp=msg.stamp,
                            floor_z_m=keyframe_floor_z(msg), instances=segmenter, config=config,
                            moving=moving)
