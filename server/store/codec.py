"""How the store encodes values in blobs: poses, object measurements and cameras.

Backends share these, so a file written by one reads the same in another.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Sequence
from typing import Any, Final

import cv2
import msgpack
import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.server.perception.types import ObjectMeasurement
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.config import to_mapping
from wardmap.shared.wire import array_to_wire, decode_keyframe, jpeg_size

_POSE_DTYPE: Final = np.dtype("<f8")
_ARRAYS: Final = ("box_xyxy", "points_camera", "T_camera_object", "T_world_camera", "T_world_object",
                  "size", "color_hist", "descriptors")


def pose_blob(T: ArrayLike) -> bytes:
    """A (4, 4) pose as the store keeps it: 16 little-endian float64, row-major (128 bytes)."""
    return np.ascontiguousarray(T, dtype=_POSE_DTYPE).tobytes()


def pose_from_blob(blob: bytes) -> NDArray[np.float64]:
    """Inverse of :func:`pose_blob`: a read-only (4, 4) float64 array."""
    T = np.frombuffer(bytes(blob), dtype=_POSE_DTYPE).astype(np.float64).reshape(4, 4)
    T.flags.writeable = False
    return T


def poses_from_blobs(blobs: list[bytes]) -> NDArray[np.float64]:
    """Many :func:`pose_blob` values as one (N, 4, 4) float64 array."""
    poses = np.frombuffer(b"".join(bytes(b) for b in blobs), dtype=_POSE_DTYPE)
    return poses.astype(np.float64).reshape(len(blobs), 4, 4)


def pack_measurement(m: ObjectMeasurement) -> bytes:
    """msgpack of a measurement without its mask (association does not read masks); arrays as
    the wire's ``{dtype, shape, data}`` maps (:func:`~wardmap.shared.wire.array_to_wire`)."""
    d: dict[str, Any] = {"keyframe": m.keyframe, "stamp": m.stamp, "category": m.category,
                         "confidence": float(m.confidence), "gt_instance": m.gt_instance}
    for name in _ARRAYS:
        d[name] = array_to_wire(np.asarray(getattr(m, name)))
    return bytes(msgpack.packb(d, use_bin_type=True))


def unpack_measurement(blob: bytes) -> ObjectMeasurement:
    """Inverse of :func:`pack_measurement` (the mask comes back empty, shape (0, 0))."""
    d = msgpack.unpackb(blob, raw=False)
    arrays = {name: _array(d[name]) for name in _ARRAYS}
    return ObjectMeasurement(
        keyframe=d["keyframe"], stamp=float(d["stamp"]), category=d["category"],
        confidence=float(d["confidence"]), mask=np.zeros((0, 0), bool), gt_instance=d["gt_instance"],
        **arrays,
    )


def pack_measurements(measurements: Sequence[ObjectMeasurement]) -> bytes:
    """A keyframe's measurements as one blob: a msgpack list of :func:`pack_measurement` blobs."""
    return bytes(msgpack.packb([pack_measurement(m) for m in measurements], use_bin_type=True))


def unpack_measurements(blob: bytes) -> list[ObjectMeasurement]:
    """Inverse of :func:`pack_measurements` (masks come back empty)."""
    return [unpack_measurement(b) for b in msgpack.unpackb(bytes(blob), raw=False)]


def _array(value: dict[str, Any]) -> NDArray[Any]:
    """A writable array of a ``{dtype, shape, data}`` map. ``dtype`` is a wire name
    (``"float64"``, data little-endian) or, in blobs written before the wire codec was used,
    numpy's ``dtype.str`` (``"<f8"``, byte order in the name). The wire's own decoder allows
    no float64, which measurements hold."""
    label = str(value["dtype"])
    dtype = np.dtype(label) if label[:1] in ("<", ">", "|", "=") else np.dtype(label).newbyteorder("<")
    array = np.frombuffer(value["data"], dtype).reshape(value["shape"])
    return array.astype(dtype.newbyteorder("="))


def camera_to_json(camera: PinholeCamera) -> str:
    """A camera as JSON text (its dataclass fields)."""
    return json.dumps(to_mapping(camera))


def camera_from_json(text: str) -> PinholeCamera:
    """Inverse of :func:`camera_to_json`."""
    d = json.loads(text)
    return PinholeCamera(**{**d, "distortion": tuple(d["distortion"])})


def without_images(payload: bytes) -> bytes:
    """A keyframe's wire bytes with its images erased (retention, ``wardmap images erase``).

    The colour JPEG becomes a black one of the same size (the wire requires a colour image
    matching the intrinsics) and the thermal raster is dropped; every other field keeps its
    bytes (poses, keypoints, depth, intrinsics), so the back-end and the mapping stage decode
    the keyframe as before, with the same features.

    Raises:
        WireError: ``payload`` is not a valid keyframe.
    """
    msg = decode_keyframe(payload)  # validates; the edit below is on the msgpack map itself
    width, height, _ = jpeg_size(msg.rgb_jpeg)
    tree = msgpack.unpackb(payload, raw=False)
    tree["rgb_jpeg"] = _black_jpeg(width, height)
    tree.pop("thermal", None)
    out = bytes(msgpack.packb(tree, use_bin_type=True))
    decode_keyframe(out)
    return out


@functools.lru_cache(maxsize=8)
def _black_jpeg(width: int, height: int) -> bytes:
    """A black colour JPEG of ``width`` x ``height`` pixels (a few KB)."""
    ok, data = cv2.imencode(".jpg", np.zeros((height, width, 3), np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 50])
    if not ok:
        raise ValueError(f"cannot JPEG-encode a {width}x{height} placeholder")
    return bytes(data.tobytes())
