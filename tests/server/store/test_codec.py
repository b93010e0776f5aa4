"""Tests of the store's blob encodings (``wardmap.server.store.codec``): measurements, poses,
cameras. Measurements written before the store used the wire's array codec must still decode."""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np

from wardmap.server.perception.types import ObjectMeasurement
from wardmap.server.store.codec import (
    camera_from_json,
    camera_to_json,
    pack_measurement,
    pose_blob,
    pose_from_blob,
    unpack_measurement,
)
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.se3 import yaw_transform

ARRAYS = ("box_xyxy", "points_camera", "T_camera_object", "T_world_camera", "T_world_object", "size",
          "color_hist", "descriptors")


def _measurement() -> ObjectMeasurement:
    rng = np.random.default_rng(0)
    return ObjectMeasurement(
        keyframe="r1/s1/0", stamp=1.5, category="door", confidence=0.9,
        box_xyxy=np.array([1.0, 2.0, 30.0, 40.0]), mask=np.ones((4, 4), bool),
        points_camera=rng.normal(size=(5, 3)).astype(np.float32),
        T_camera_object=yaw_transform(0.1, 0.2, 0.3, 0.4), T_world_camera=np.eye(4),
        T_world_object=yaw_transform(1.0, 2.0, -0.5, 0.3),
        size=np.array([1.0, 0.1, 2.0]), color_hist=np.full(8, 0.125, np.float32),
        descriptors=np.arange(64, dtype=np.uint8).reshape(2, 32), gt_instance=7,
    )


def _pack_as_before(m: ObjectMeasurement) -> bytes:
    """The measurement blob as wardmap wrote it up to 5ab2547 (``server/pipeline.py``): numpy's
    ``dtype.str`` as the dtype, native-order bytes."""
    d: dict[str, Any] = {"keyframe": m.keyframe, "stamp": m.stamp, "category": m.category,
                         "confidence": float(m.confidence), "gt_instance": m.gt_instance}
    for name in ARRAYS:
        a = np.ascontiguousarray(getattr(m, name))
        d[name] = {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}
    return bytes(msgpack.packb(d, use_bin_type=True))


def _assert_same(m: ObjectMeasurement, back: ObjectMeasurement) -> None:
    assert back.mask.shape == (0, 0)
    assert (back.keyframe, back.stamp, back.category, back.confidence, back.gt_instance) == (
        m.keyframe, m.stamp, m.category, m.confidence, m.gt_instance)
    for name in ARRAYS:
        a, b = getattr(m, name), getattr(back, name)
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), name
        assert b.flags.writeable, name


def test_measurement_round_trip() -> None:
    """Stored measurements come back equal, without their masks; arrays are in the wire's format."""
    m = _measurement()
    blob = pack_measurement(m)
    _assert_same(m, unpack_measurement(blob))
    d = msgpack.unpackb(blob, raw=False)
    assert d["T_world_object"]["dtype"] == "float64" and d["descriptors"]["dtype"] == "uint8"


def test_measurement_blobs_of_the_former_format_decode_the_same() -> None:
    """A blob written before the wire codec was used decodes to the same measurement as a new one."""
    m = _measurement()
    old = _pack_as_before(m)
    assert old != pack_measurement(m)
    _assert_same(m, unpack_measurement(old))


def test_pose_and_camera_round_trip() -> None:
    T = yaw_transform(1.0, -2.0, 0.7, 0.5)
    blob = pose_blob(T)
    assert len(blob) == 128 and np.array_equal(pose_from_blob(blob), T)
    assert not pose_from_blob(blob).flags.writeable
    camera = PinholeCamera(640, 480, 525.0, 524.0, 319.5, 239.5, (0.1, -0.2, 0.0, 0.0, 0.01))
    assert camera_from_json(camera_to_json(camera)) == camera
