"""One keyframe through perception (``server/perception/keyframe.py``): the order of the steps,
what each leaves out and counts, ground truth, and keyframes on the wire.

The scene: the room of ``perception_scenes.room_depth`` seen by a level camera 1.05 m above
the floor (``T_LEVEL``; floor at z = 0), with a chair-high box standing on the floor, a box
hanging on the wall, a strip of the wall at the image border, a strip of the floor and a
person-sized box; a fake segmenter names them.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from perception_scenes import BGR, CAMERA, T_LEVEL, box_instance, room_depth

from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.perception.floor import LeftOut
from wardmap.server.perception.keyframe import (
    ORACLE,
    KeyframePerception,
    decode_keyframe_images,
    keyframe_camera,
    keyframe_floor_z,
    keyframe_map_pose,
    measure_keyframe,
    measure_keyframe_msg,
)
from wardmap.server.perception.types import Instance
from wardmap.shared.errors import GeometryError, WireError
from wardmap.shared.se3 import yaw_transform
from wardmap.shared.wire import Intrinsics, KeyframeMsg, Keypoints, PackedRaster, encode_depth

MOVING = ("person",)


def scene() -> tuple[np.ndarray, dict[str, Instance]]:
    """Depth (H, W) of the room and its instances by name."""
    depth = room_depth()
    depth[150:199, 100:140] = 3.0  # a chair-high box on the floor, 1 m in front of the wall
    depth[106:152, 200:216] = 2.9  # a box hanging on the wall, clear of the floor
    depth[222:230, 250:300] = 3.5  # a strip along the floor
    depth[60:199, 230:250] = 3.2  # a person-sized box standing on the floor
    return depth, {
        "chair": box_instance("chair", slice(150, 199), slice(100, 140)),
        "floating": box_instance("chair", slice(106, 152), slice(200, 216)),
        "wall strip": box_instance("cabinet", slice(130, 200), slice(0, 20)),
        "floor strip": box_instance("cart", slice(222, 230), slice(250, 300)),
        "person": box_instance("person", slice(60, 199), slice(230, 250)),
    }


class Finds:
    """A segmenter that finds the given instances, whatever the image; counts its calls."""

    def __init__(self, instances: list[Instance]) -> None:
        self.instances = instances
        self.calls = 0

    def __call__(self, bgr: np.ndarray, depth_m: np.ndarray | None) -> list[Instance]:
        self.calls += 1
        return list(self.instances)


def run(instances: object, depth: np.ndarray, floor_z_m: float | None = 0.0,
        config: PerceptionConfig | None = None, **kw: object) -> KeyframePerception:
    """``measure_keyframe`` of the scene's image and camera, the floor at ``floor_z_m``."""
    return measure_keyframe(BGR, depth, CAMERA, T_LEVEL, keyframe="room/1", stamp=1.0, floor_z_m=floor_z_m,
                            instances=instances, config=config or PerceptionConfig(), moving=MOVING, **kw)


def test_each_step_leaves_out_its_own_and_counts_them() -> None:
    """Of the five instances only the standing chair is measured: the person is left out as
    moving, the floating chair, the wall strip and the floor strip by their floor checks,
    each counted once in its own count."""
    depth, inst = scene()
    seg = Finds(list(inst.values()))
    out = run(seg, depth)
    assert seg.calls == 1
    assert (out.found, out.moving, out.left_out) == (5, 1, LeftOut(1, 1, 1))
    assert [m.category for m in out.measurements] == ["chair"]
    assert out.skipped == [] and out.skipped_by_kind() == {}
    (m,) = out.measurements
    assert m.keyframe == "room/1" and m.stamp == 1.0 and m.gt_instance is None
    np.testing.assert_array_equal(m.mask, inst["chair"].mask)
    np.testing.assert_allclose(m.T_world_camera, T_LEVEL)


def test_instances_given_or_found_give_the_same_result() -> None:
    """Instances found already (a caller that timed its segmenter) take the same steps as the
    segmenter's: same counts, same measurements."""
    depth, inst = scene()
    a, b = run(Finds(list(inst.values())), depth), run(list(inst.values()), depth)
    assert (a.found, a.moving, a.left_out) == (b.found, b.moving, b.left_out)
    assert len(a.measurements) == len(b.measurements) == 1
    np.testing.assert_array_equal(a.measurements[0].T_world_object, b.measurements[0].T_world_object)
    np.testing.assert_array_equal(a.measurements[0].points_camera, b.measurements[0].points_camera)


def test_moving_classes_leave_before_the_floor_checks() -> None:
    """A person hanging in the air where the floor checks also look for floating persons: it is
    counted as moving, not as floating (moving classes leave first), and the checks still
    leave out the floating chair."""
    depth, inst = scene()
    flying = dataclasses.replace(inst["floating"], category="person")
    config = PerceptionConfig(floor_gap_m=(("chair", 0.6), ("person", 0.6)))
    out = run([flying, inst["floating"], inst["chair"]], depth, config=config)
    assert (out.found, out.moving, out.left_out) == (3, 1, LeftOut(1, 0, 0))
    assert [m.category for m in out.measurements] == ["chair"]


def test_without_a_floor_nothing_is_checked() -> None:
    """A hand-held camera (floor unknown): only the person is left out; the floating chair and
    the strips are measured or skipped by measurement."""
    depth, inst = scene()
    out = run(list(inst.values()), depth, floor_z_m=None)
    assert (out.found, out.moving, out.left_out) == (5, 1, LeftOut(0, 0, 0))
    assert len(out.measurements) + len(out.skipped) == 4


def test_ground_truth_is_neither_split_nor_checked() -> None:
    """With ``source`` "oracle" a floating chair, a wall strip and a door mask as wide as two
    doors are measured as given (ground truth is one object each, where it is); the same
    instances from the network lose the floating chair and the strip, and the door is cut in
    two. People leave either way."""
    depth, inst = scene()
    depth[10:50, 30:270] = 3.0  # the upper part of two doors side by side, 1 m before the wall
    doors = box_instance("door", slice(10, 50), slice(30, 270))  # 2.7 m wide at 3 m
    given = [doors, inst["floating"], inst["wall strip"], inst["person"]]
    truth = run(given, depth, source=ORACLE)
    assert (truth.found, truth.moving, truth.left_out) == (4, 1, LeftOut(0, 0, 0))
    assert [m.category for m in truth.measurements] == ["door", "chair", "cabinet"]
    network = run(given, depth, source="model")
    assert (network.found, network.moving, network.left_out) == (5, 1, LeftOut(1, 1, 0))
    assert [m.category for m in network.measurements] == ["door", "door"]
    # A detector's instances are not split either, but are checked against the floor.
    detector = run(given, depth, source="yolox:x.onnx")
    assert (detector.found, detector.left_out) == (4, LeftOut(1, 1, 0))


def test_label_image_sets_the_ground_truth_ids() -> None:
    """With the simulator's label image each measured instance takes the id under most of its mask."""
    depth, inst = scene()
    labels = np.zeros(depth.shape, np.uint16)
    labels[150:199, 100:140] = 7
    (m,) = run([inst["chair"]], depth, instance_ids=labels).measurements
    assert m.gt_instance == 7
    (m,) = run([inst["chair"]], depth).measurements
    assert m.gt_instance is None


def test_images_and_pose_of_the_wrong_shape_are_refused() -> None:
    depth, inst = scene()
    seg = Finds([inst["chair"]])
    with pytest.raises(GeometryError, match="BGR image"):
        measure_keyframe(BGR[:10], depth, CAMERA, T_LEVEL, keyframe="k", stamp=0.0, floor_z_m=0.0,
                         instances=seg, config=PerceptionConfig(), moving=MOVING)
    with pytest.raises(GeometryError, match="depth"):
        measure_keyframe(BGR, depth[:, :10], CAMERA, T_LEVEL, keyframe="k", stamp=0.0, floor_z_m=0.0,
                         instances=seg, config=PerceptionConfig(), moving=MOVING)
    with pytest.raises(GeometryError, match="T_world_camera"):
        measure_keyframe(BGR, depth, CAMERA, np.eye(3), keyframe="k", stamp=0.0, floor_z_m=0.0,
                         instances=seg, config=PerceptionConfig(), moving=MOVING)
    assert seg.calls == 0  # refused before the segmenter runs


# ---------------------------------------------------------------------------- keyframes on the wire


def keyframe(depth: np.ndarray, *, T_odom_base: np.ndarray | None, T_map_odom: np.ndarray | None,
             stride: int = 2, bgr: np.ndarray = BGR) -> KeyframeMsg:
    """A keyframe message of the scene: the camera 1.05 m above the odom frame's floor, depth
    sent at 1/``stride``."""
    ok, jpg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert ok
    empty = Keypoints(np.zeros((0, 2), np.float32), np.zeros(0, np.int16), np.zeros(0, np.float32),
                      np.zeros(0, np.float32), np.zeros((0, 32), np.uint8))
    return KeyframeMsg(robot_id="r1", session_id="s1", seq=3, stamp=2.5, T_odom_camera=T_LEVEL,
                       pose_source="rgb", keypoints=empty, rgb_jpeg=jpg.tobytes(),
                       depth=PackedRaster(*encode_depth(depth[::stride, ::stride])),
                       intrinsics=Intrinsics.from_camera(CAMERA, 5000.0), T_odom_base=T_odom_base,
                       T_map_odom=T_map_odom)


def test_a_keyframe_message_is_decoded_at_the_colour_size() -> None:
    """The colour image comes back in BGR order at the intrinsics' size; depth sent at 1/2 is
    repeated to it: pixel (y, x) takes (y // 2, x // 2)."""
    depth = np.random.default_rng(0).uniform(0.5, 4.0, (CAMERA.height, CAMERA.width)).astype(np.float32)
    red_blue = np.zeros_like(BGR)
    red_blue[:, : CAMERA.width // 2] = (0, 0, 255)
    red_blue[:, CAMERA.width // 2 :] = (255, 0, 0)
    msg = keyframe(depth, T_odom_base=None, T_map_odom=None, bgr=red_blue)
    bgr, full, camera = decode_keyframe_images(msg)
    assert camera == keyframe_camera(msg) == CAMERA
    assert bgr.dtype == np.uint8 and bgr.shape == BGR.shape
    assert np.abs(bgr[:, 8:150].astype(np.int16) - red_blue[:, 8:150]).max() < 8  # JPEG, quality 100
    assert np.abs(bgr[:, 170:-8].astype(np.int16) - red_blue[:, 170:-8]).max() < 8
    assert full.shape == depth.shape and full.dtype == np.float32
    np.testing.assert_allclose(full, np.repeat(np.repeat(depth[::2, ::2], 2, 0), 2, 1), atol=1e-3)


def test_map_pose_and_floor_of_a_keyframe() -> None:
    """The map pose is ``T_map_odom @ T_odom_camera`` (odom = map for a session not on the map);
    the floor is the base's height in the map; no base, no floor."""
    depth, _ = scene()
    T_map_odom = yaw_transform(2.0, -1.0, 0.5, z=0.3)
    base = np.eye(4)
    on_map = keyframe(depth, T_odom_base=base, T_map_odom=T_map_odom)
    np.testing.assert_allclose(keyframe_map_pose(on_map), T_map_odom @ T_LEVEL)
    assert keyframe_floor_z(on_map) == pytest.approx(0.3)
    off_map = keyframe(depth, T_odom_base=base, T_map_odom=None)
    np.testing.assert_allclose(keyframe_map_pose(off_map), T_LEVEL)
    assert keyframe_floor_z(off_map) == pytest.approx(0.0)
    assert keyframe_floor_z(keyframe(depth, T_odom_base=None, T_map_odom=T_map_odom)) is None


def test_a_keyframe_message_goes_the_same_way_in_the_map_frame() -> None:
    """``measure_keyframe_msg`` is ``measure_keyframe`` on the decoded images, in the map frame,
    with the floor under the robot base: the floating chair is left out on a robot and kept
    with a hand-held camera."""
    depth, inst = scene()
    seg = Finds([inst["chair"], inst["floating"]])
    T_map_odom = yaw_transform(2.0, -1.0, 0.5, z=0.3)
    msg = keyframe(depth, T_odom_base=np.eye(4), T_map_odom=T_map_odom, stride=1)
    out = measure_keyframe_msg(msg, "r1/s1/3", segmenter=seg, config=PerceptionConfig(), moving=MOVING)
    assert out.left_out == LeftOut(1, 0, 0) and [m.category for m in out.measurements] == ["chair"]
    (m,) = out.measurements
    assert (m.keyframe, m.stamp) == ("r1/s1/3", 2.5)
    np.testing.assert_allclose(m.T_world_camera, T_map_odom @ T_LEVEL)
    bgr, full, camera = decode_keyframe_images(msg)
    same = measure_keyframe(bgr, full, camera, T_map_odom @ T_LEVEL, keyframe="r1/s1/3", stamp=2.5,
                            floor_z_m=0.3, instances=seg, config=PerceptionConfig(), moving=MOVING)
    np.testing.assert_array_equal(same.measurements[0].T_world_object, m.T_world_object)
    handheld = keyframe(depth, T_odom_base=None, T_map_odom=T_map_odom, stride=1)
    out = measure_keyframe_msg(handheld, "r1/s1/3", segmenter=seg, config=PerceptionConfig(), moving=MOVING)
    assert out.left_out == LeftOut(0, 0, 0) and len(out.measurements) + len(out.skipped) == 2


def test_a_keyframe_without_intrinsics_is_refused() -> None:
    depth, _ = scene()
    msg = dataclasses.replace(keyframe(depth, T_odom_base=None, T_map_odom=None), intrinsics=None,
                              calib_ref="rig-1")
    with pytest.raises(WireError, match="calib_ref"):
        keyframe_camera(msg)
