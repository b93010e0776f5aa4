"""The wire message of one keyframe, built from a tracked frame.

One builder for the edge daemon (:class:`~wardmap.edge.agent.EdgeAgent`) and the offline
tools (``wardmap.tools.keyframes``), so that a keyframe replayed from a data set is
byte-identical to the one the robot would have sent.

Content (docs/wire.md): the tracker's own ORB features of the keyframe after dynamic-point
removal, the strongest ``max_keypoints`` of them (a keyframe the tracker made without RGB
features gets ORB extracted here, without map point ids), each with the depth at its pixel
(0 = none) and the id of the tracker's map point it observed or made (-1 = none); the colour
image as JPEG; depth at 1/``depth_stride`` resolution (1 when the image size is not
divisible by it); thermal at 1/``thermal_stride`` resolution quantised to
``thermal_unit_k`` when due (:func:`thermal_due`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.edge.privacy import dilate, mask_in_other_camera, redact_rgb, redact_thermal
from wardmap.edge.tracker import Tracker, TrackResult
from wardmap.shared.dataset import Frame
from wardmap.shared.errors import WardmapError
from wardmap.shared.se3 import inverse
from wardmap.shared.wire import (
    POINT_ID_MODULUS,
    Intrinsics,
    KeyframeMsg,
    Keypoints,
    PackedRaster,
    encode_depth,
    encode_thermal,
)

if TYPE_CHECKING:  # agent.py imports this module; the config type is only named here
    from wardmap.edge.agent import AgentConfig

__all__ = ["build_keyframe_msg", "thermal_due"]


def thermal_due(pose_source: str, keyframes_before: int, every: int) -> bool:
    """Whether a keyframe carries thermal: every ``every``-th keyframe of a session (counting
    from 0 with ``keyframes_before`` = keyframes already made; ``every`` = 0: never by count)
    and every keyframe whose pose came from thermal tracking."""
    return pose_source == "thermal" or (every > 0 and keyframes_before % every == 0)


def build_keyframe_msg(
    frame: Frame,
    res: TrackResult,
    tracker: Tracker,
    *,
    T_odom_base: NDArray[np.float64] | None,
    intrinsics: Intrinsics,
    robot_id: str,
    session_id: str,
    seq: int,
    config: AgentConfig,
    with_thermal: bool,
    T_map_odom: NDArray[np.float64] | None = None,
    person: NDArray[np.bool_] | None = None,
) -> KeyframeMsg:
    """The wire message of keyframe ``seq`` of session ``(robot_id, session_id)``.

    Args:
        frame: the keyframe's frame (``rgb`` uint8 (H, W, 3) RGB, ``depth_m`` float32 (H, W)).
        res: the tracker's result for ``frame`` (``T_world_camera`` is ``T_odom_camera``).
        tracker: the tracker that made ``res`` (its ORB extractor serves keyframes without features).
        T_odom_base: (4, 4) wheel-odometry pose at the frame's stamp, or None.
        intrinsics: the colour camera's intrinsics and the data set's depth scale.
        config: the agent settings read here: ``max_keypoints``, ``jpeg_quality``,
            ``depth_stride``, ``thermal_stride``, ``thermal_unit_k``.
        with_thermal: attach the thermal image (if the frame has one); see :func:`thermal_due`.
        T_map_odom: (4, 4) the session's odom frame in the map (a robot started at a known map pose).
        person: bool (H, W) the frame's person pixels (:func:`wardmap.edge.privacy.person_mask`),
            or None when the label source had no labels for it. Unless ``config.privacy`` is
            ``off``, the images are redacted inside this mask grown by ``privacy_dilate_px``
            (None: the whole image, since nobody can say where the people are); the keypoints
            are the tracker's, computed on the raw frame.

    Raises:
        WardmapError: the colour image cannot be JPEG-encoded.
    """
    depth = np.nan_to_num(frame.depth_m, nan=0.0, posinf=0.0, neginf=0.0)
    feats, point_id = res.features, res.point_ids
    if feats is None:
        feats = tracker.orb.extract(np.asarray(cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY), np.uint8))
        point_id = None
    if len(feats.uv) > config.max_keypoints:
        strongest = np.sort(np.argsort(-feats.response, kind="stable")[: config.max_keypoints])
        feats = feats.select(strongest)
        point_id = None if point_id is None else point_id[strongest]
    h, w = depth.shape
    col = np.clip(np.rint(feats.uv[:, 0]).astype(np.int64), 0, w - 1)
    row = np.clip(np.rint(feats.uv[:, 1]).astype(np.int64), 0, h - 1)
    kp_depth = np.maximum(depth[row, col], 0.0).astype(np.float32)
    keypoints = Keypoints(
        uv=np.ascontiguousarray(feats.uv, np.float32),
        octave=feats.octave.astype(np.int16),
        angle_deg=np.clip(feats.angle_deg, 0.0, 360.0).astype(np.float32),
        depth_m=kp_depth,
        descriptors=np.ascontiguousarray(feats.descriptors, np.uint8),
        point_id=None if point_id is None else np.where(
            point_id >= 0, point_id % POINT_ID_MODULUS, -1).astype(np.int32),
    )
    rgb, thermal_k = frame.rgb, frame.thermal_k
    if config.privacy != "off":
        mask = (np.ones(depth.shape, bool) if person is None
                else dilate(np.asarray(person, bool), config.privacy_dilate_px))
        rgb = redact_rgb(rgb, mask, config.privacy)
        if thermal_k is not None and with_thermal:
            calib = tracker.calib
            if person is None or calib.thermal is None or calib.T_rgb_thermal is None:
                thermal_k = None  # cannot place the people in the thermal image: not sent
            else:
                mask_th = mask_in_other_camera(mask, depth, tracker.cam, calib.thermal,
                                               inverse(calib.T_rgb_thermal), margin_px=0)
                thermal_k = redact_thermal(thermal_k, mask_th)
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, config.jpeg_quality])
    if not ok:
        raise WardmapError(f"cannot JPEG-encode the colour image of frame {frame.index}")
    s = config.depth_stride if h % config.depth_stride == 0 and w % config.depth_stride == 0 else 1
    thermal = None
    if thermal_k is not None and with_thermal:
        th = np.nan_to_num(thermal_k, nan=0.0, posinf=0.0, neginf=0.0)
        ts = config.thermal_stride
        if th.shape[0] % ts or th.shape[1] % ts:
            ts = 1
        thermal = PackedRaster(*encode_thermal(th[::ts, ::ts], unit_k=config.thermal_unit_k))
    return KeyframeMsg(
        robot_id=robot_id,
        session_id=session_id,
        seq=seq,
        stamp=float(frame.stamp),
        T_odom_camera=res.T_world_camera,
        pose_source=res.source,
        keypoints=keypoints,
        rgb_jpeg=jpeg.tobytes(),
        depth=PackedRaster(*encode_depth(depth[::s, ::s])),
        intrinsics=intrinsics,
        T_odom_base=T_odom_base,
        thermal=thermal,
        T_map_odom=T_map_odom,
    )
