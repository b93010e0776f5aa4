"""Synthetic test inputs shared by test modules: keyframes, malformed payloads, object measurements.

Every builder is seeded through the ``np.random.Generator`` it is given (or is deterministic),
so a test that builds the same input twice gets the same bytes.

Keyframes (``wardmap.shared.wire``):
    :func:`keyframe` is the small valid keyframe tests store, send and fuzz (a W x H noise JPEG,
    depth at half resolution, a few keypoints, intrinsics, identity pose); :func:`walk` numbers
    copies of it; :func:`full_keyframe` sets every optional part (thermal, base and map poses,
    or a calibration reference instead of intrinsics) with random values, for round trips.
Payloads: :func:`mutate` makes one seeded malformed variant of an encoded message.
Measurements (``wardmap.server.association``): :func:`measurement` is an object box seen by
    :data:`CAMERA` from a pose made with :func:`camera_looking_along_y`; :func:`object_pose`.
"""

from __future__ import annotations

import copy
import functools
import zlib
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import cv2
import msgpack
import numpy as np

from wardmap.server.association.geometry import project_box
from wardmap.server.perception.types import ObjectMeasurement
from wardmap.shared import wire
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.se3 import inverse, make_transform, se3_exp
from wardmap.shared.wire import Intrinsics, KeyframeMsg, Keypoints, PackedRaster

# --------------------------------------------------------------------------- keyframes

W, H = 64, 48
"""Colour image size of the synthetic keyframes (pixels)."""
TW, TH = 32, 24
"""Thermal image size of :func:`full_keyframe` (pixels)."""
T0 = 1_714_557_600.0
"""Stamp of the synthetic keyframes: 2024-05-01 10:00 UTC (seconds)."""


def random_pose(rng: np.random.Generator) -> np.ndarray:
    """A random rigid transform (4, 4): exp of a standard normal twist."""
    return se3_exp(rng.normal(size=6))


def noise_jpeg(rng: np.random.Generator, width: int = W, height: int = H, channels: int = 3) -> bytes:
    """A JPEG (quality 85) of uniform noise, ``channels`` 3 (colour) or 1 (grey)."""
    shape = (height, width, channels) if channels > 1 else (height, width)
    img = rng.integers(0, 256, shape, dtype=np.uint8)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
    if not ok:
        raise RuntimeError("OpenCV could not encode a JPEG")
    return bytes(buf.tobytes())


def keypoints(rng: np.random.Generator, n: int, width: int = W, height: int = H) -> Keypoints:
    """``n`` random keypoints inside a ``width`` x ``height`` image; a fifth have no depth (0 m)."""
    return Keypoints(
        uv=(rng.random((n, 2)) * [width - 1, height - 1]).astype(np.float32),
        octave=rng.integers(0, 8, n).astype(np.int8),
        angle_deg=(rng.random(n) * 360).astype(np.float32),
        depth_m=np.where(rng.random(n) < 0.2, 0, rng.uniform(0.3, 6.0, n)).astype(np.float32),
        descriptors=rng.integers(0, 256, (n, 32), dtype=np.uint8),
    )


def depth_image(rng: np.random.Generator, width: int = W, height: int = H) -> np.ndarray:
    """(height, width) float32 depth in metres, uniform in [0.3, 8), a tenth of it holes (0)."""
    d = rng.uniform(0.3, 8.0, (height, width)).astype(np.float32)
    d[rng.random((height, width)) < 0.1] = 0.0
    return d


def thermal_image(rng: np.random.Generator) -> np.ndarray:
    """(TH, TW) float32 temperatures in kelvin, uniform in [290, 315)."""
    return rng.uniform(290.0, 315.0, (TH, TW)).astype(np.float32)


def keyframe(rng: np.random.Generator, *, robot_id: str = "r1", session_id: str = "s1",
             n_keypoints: int = 4) -> KeyframeMsg:
    """A small valid keyframe: seq 0 at :data:`T0`, identity ``T_odom_camera``, a W x H noise JPEG,
    depth at half resolution, ``n_keypoints`` keypoints, pinhole intrinsics (fx = fy = 50 px, no
    distortion), no thermal and no base or map pose. Other keys and poses: ``dataclasses.replace``
    or :func:`walk`."""
    return KeyframeMsg(
        robot_id=robot_id,
        session_id=session_id,
        seq=0,
        stamp=T0,
        T_odom_camera=np.eye(4),
        pose_source="rgb",
        keypoints=keypoints(rng, n_keypoints),
        rgb_jpeg=noise_jpeg(rng),
        depth=PackedRaster(*wire.encode_depth(depth_image(rng, W // 2, H // 2))),
        intrinsics=Intrinsics(W, H, 50.0, 50.0, 31.5, 23.5, (0.0, 0.0, 0.0, 0.0, 0.0), 5000.0),
    )


def walk(base: KeyframeMsg, n: int) -> list[KeyframeMsg]:
    """``n`` copies of ``base`` with seq 0..n-1, each one second and one metre (odom +x) after
    the one before: stamp ``base.stamp + seq``, ``T_odom_camera`` a translation (seq, 0, 0) m."""
    return [
        replace(base, seq=i, stamp=base.stamp + i, T_odom_camera=make_transform(np.eye(3), [i, 0, 0]))
        for i in range(n)
    ]


def full_keyframe(rng: np.random.Generator, *, thermal: bool = True, intrinsics: bool = True,
                  base: bool = True, n: int = 20) -> KeyframeMsg:
    """A valid keyframe of robot_0 with random seq, stamp near :data:`T0`, random poses and ``n``
    keypoints; thermal when ``thermal``; intrinsics with distortion when ``intrinsics``, else a
    calibration reference; ``T_odom_base`` and ``T_map_odom`` when ``base``; map point ids on
    the keypoints (every fifth -1)."""
    ids = np.where(np.arange(n) % 5 == 0, -1, np.arange(n) + 1000).astype(np.int32)
    return KeyframeMsg(
        robot_id="robot_0",
        session_id="2024-05-01T10.00_a",
        seq=int(rng.integers(0, 2**40)),
        stamp=T0 + float(rng.random()),
        T_odom_camera=random_pose(rng),
        pose_source="rgb",
        keypoints=replace(keypoints(rng, n), point_id=ids),
        rgb_jpeg=noise_jpeg(rng),
        depth=PackedRaster(*wire.encode_depth(depth_image(rng))),
        intrinsics=Intrinsics(W, H, 52.5, 52.5, 31.5, 23.5, (0.1, -0.2, 0.001, 0.002, 0.05), 5000.0)
        if intrinsics else None,
        calib_ref=None if intrinsics else "sha256:" + "ab" * 32,
        T_odom_base=random_pose(rng) if base else None,
        thermal=PackedRaster(*wire.encode_thermal(thermal_image(rng))) if thermal else None,
        T_map_odom=random_pose(rng) if base else None,
    )


# --------------------------------------------------------------------------- malformed payloads

FUZZ_LEAVES: tuple[Any, ...] = (
    None, True, False, -1, 0, 1, 2**63, 2**64 - 1, -(2**63), 1.5, -0.0, float("nan"), float("inf"),
    "", "x" * 300, "wardmap.keyframe", b"", b"\xff\xd8" + bytes(30), [], {}, [1, 2, 3], {"a": 1},
    [0.0, 0.0, 0.0, 1.0], {"dtype": "uint8", "shape": [0], "data": b""},
)
"""Values of every msgpack type that :func:`mutate` puts in place of a field or adds."""


def pack(tree: Any) -> bytes:
    """msgpack bytes of ``tree`` (binary as bin, strings as str), as the wire encodes."""
    return bytes(msgpack.packb(tree, use_bin_type=True))


def leaf_paths(node: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every key path (dict keys and list indices) below ``node``, parents before children."""
    out = [path] if path else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += leaf_paths(v, (*path, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += leaf_paths(v, (*path, i))
    return out


def mutate(payload: bytes, rng: np.random.Generator, *, leaves: Sequence[Any] = FUZZ_LEAVES,
           random_payloads: bool = False) -> bytes:
    """One seeded malformed variant of the msgpack ``payload``: bit flips, a truncation, inserted
    bytes, or a structural edit of the decoded tree (a field or subtree replaced by one of
    ``leaves``, deleted, or an unknown key added).

    With ``random_payloads`` (payloads sent over zenoh) whole random payloads are one more kind,
    and a truncation never leaves the payload empty.
    """
    kinds: list[Callable[[], bytes]] = [
        lambda: _flip_bits(payload, rng),
        lambda: payload[: int(rng.integers(1 if random_payloads else 0, len(payload)))],
        lambda: _insert_bytes(payload, rng),
    ]
    if random_payloads:
        kinds.append(lambda: rng.integers(0, 256, int(rng.integers(1, 3000)), dtype=np.uint8).tobytes())
    n_bytes_kinds = len(kinds)
    kind = int(rng.integers(0, n_bytes_kinds + 3))
    if kind < n_bytes_kinds:
        return bytes(kinds[kind]())
    tree = msgpack.unpackb(payload, raw=False)
    paths = leaf_paths(tree)
    path = paths[int(rng.integers(0, len(paths)))]
    parent = tree
    for p in path[:-1]:
        parent = parent[p]
    edit = kind - n_bytes_kinds
    if edit == 0:  # replace a value (leaf or subtree) with a random value of a random type
        parent[path[-1]] = copy.deepcopy(leaves[int(rng.integers(0, len(leaves)))])
    elif edit == 1:  # delete a key or list item
        del parent[path[-1]]
    else:  # add an unknown key next to a random one
        target = parent if isinstance(parent, dict) else tree
        target["extra"] = leaves[int(rng.integers(0, len(leaves)))]
    return pack(tree)


def _flip_bits(payload: bytes, rng: np.random.Generator) -> bytes:
    buf = bytearray(payload)
    for _ in range(int(rng.integers(1, 8))):
        i = int(rng.integers(0, len(buf)))
        buf[i] ^= 1 << int(rng.integers(0, 8))
    return bytes(buf)


def _insert_bytes(payload: bytes, rng: np.random.Generator) -> bytes:
    i = int(rng.integers(0, len(payload) + 1))
    noise = rng.integers(0, 256, int(rng.integers(1, 16)), dtype=np.uint8).tobytes()
    return payload[:i] + noise + payload[i:]


# --------------------------------------------------------------------------- object measurements

CAMERA = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
"""The camera of :func:`measurement`: 640 x 480, f = 525 px, no distortion."""
CHAIR_SIZE = np.array([0.46, 0.46, 0.93])
"""A chair's box (x, y, z) in metres, the default size of :func:`measurement`."""


def camera_looking_along_y(x: float, y: float = 0.0, z: float = 0.8) -> np.ndarray:
    """T_world_camera (4, 4) of a camera at (x, y, z) looking along world +y (x right, z up in world)."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # columns: cam x, y, z in world
    return make_transform(R, [x, y, z])


def object_pose(x: float, y: float, z: float = 0.465, yaw: float = 0.0) -> np.ndarray:
    """T_world_object (4, 4) of a box centred at (x, y, z) m, turned ``yaw`` rad about world z."""
    c, s = np.cos(yaw), np.sin(yaw)
    return make_transform([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], [x, y, z])


MeasurementFactory = Callable[..., ObjectMeasurement]


def measurement(
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
    """A measurement of a ``size`` box at ``T_world_object`` moved by ``offset`` (m, world; the
    position noise), seen by :data:`CAMERA` at ``T_world_camera``: its projected box, a flat
    colour histogram, no mask or points; ``gt`` is its ground-truth object.

    Raises:
        ValueError: the box is not in view.
    """
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


# --------------------------------------------------------------------------- hostile keyframes


def with_jpeg_size(jpeg: bytes, width: int, height: int) -> bytes:
    """``jpeg`` whose baseline SOF0 header declares ``width`` x ``height`` (the data is unchanged:
    only a decoder that trusts the header would allocate that much)."""
    at = jpeg.index(b"\xff\xc0")
    return jpeg[: at + 5] + height.to_bytes(2, "big") + width.to_bytes(2, "big") + jpeg[at + 9 :]


@functools.lru_cache(maxsize=4)
def zero_raster_stream(width: int, height: int) -> bytes:
    """A valid ``delta16-zlib`` stream of a ``width`` x ``height`` all-zero raster, made 1 MiB at
    a time (an 8192x8192 one is 128 MiB inflated and about 130 KB compressed)."""
    z = zlib.compressobj(9)
    total, chunk = 2 * width * height, bytes(2**20)
    out = [z.compress(chunk[: min(len(chunk), total - i)]) for i in range(0, total, len(chunk))]
    return b"".join(out) + z.flush()


def raster_bomb(rng: np.random.Generator, side: int = 8192) -> bytes:
    """A small, well-formed keyframe payload (about 300 KB) whose colour header, depth and thermal
    rasters all declare ``side`` x ``side`` pixels, each raster a valid stream of that size."""
    tree = dict(msgpack.unpackb(wire.encode(full_keyframe(rng, intrinsics=False)), raw=False))
    tree["rgb_jpeg"] = with_jpeg_size(tree["rgb_jpeg"], side, side)
    for name in ("depth", "thermal"):
        tree[name] = {**tree[name], "width": side, "height": side, "data": zero_raster_stream(side, side)}
    return pack(tree)
