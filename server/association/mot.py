"""Multi-object tracking inside one keyframe group (paper 000 Sec. III-A-1).

The paper tracks with FairMOT; here the keyframes of a group already carry 3D
measurements (class, pose, size, appearance; Eq. 1), so tracking is frame-to-frame
Hungarian assignment (``scipy.optimize.linear_sum_assignment``) of tracks to the next
keyframe's measurements on a cost that combines

- 3D distance between the track's centre (mean of its measurements' centres, or its last
  one) and the measurement's centre, less the partial-view slack (half the difference of
  the two boxes' extents),
- reprojected box overlap: the track's last 3D box projected into the new keyframe with
  its camera pose and intrinsics, IoU with the measurement's pixel box,
- appearance: colour-histogram intersection and ORB descriptor matching,

with class disagreement forbidden and a distance gate. Unmatched measurements start new
tracks; every track of the group becomes a group-level landmark ``O^G_{n,i}``.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from wardmap.server.association.geometry import (
    box_iou,
    is_truncated,
    partial_view_slack,
    project_box,
    world_extents,
)
from wardmap.server.perception.types import ObjectMeasurement
from wardmap.shared.camera import PinholeCamera

__all__ = ["GroupLandmark", "KeyframeView", "MotConfig", "appearance_similarity", "track_group"]

F64 = NDArray[np.float64]
_FORBIDDEN = 1e6


@dataclass(frozen=True)
class MotConfig:
    """Cost and gates of the in-group tracker."""

    max_distance_m: float = 0.45
    """Gate: a track and a measurement further apart (centres, metres) never match."""
    max_distance_partial_m: float = 0.8
    """The gate when either box touches the image border (partly seen: centre biased)."""
    border_px: float = 3.0
    """A box within this many pixels of the image border marks a partly seen object."""
    size_slack: float = 1.0
    """Partial-view slack on the distance (``geometry.partial_view_slack``); 0 turns it off."""
    track_reference: Literal["last", "mean"] = "mean"
    """Track centre for the distance: its last measurement's, or the mean of its measurements'
    (objects are static: averaging suppresses measurement and pose noise)."""
    weight_distance: float = 1.0
    """Weight of ``distance / max_distance_m`` in the cost."""
    weight_iou: float = 1.0
    """Weight of ``1 - IoU`` (track box reprojected into the new keyframe vs measured box)."""
    weight_appearance: float = 0.5
    """Weight of ``1 - appearance similarity``."""
    max_cost: float = 1.8
    """Assigned pairs costing more than this are refused (the measurement starts a new track)."""
    orb_ratio: float = 0.8
    """Lowe ratio for ORB descriptor matches (Hamming distance)."""
    orb_max_distance: int = 64
    """ORB matches with a larger Hamming distance are not counted."""

    def __post_init__(self) -> None:
        if self.max_distance_m <= 0 or self.max_cost <= 0:
            raise ValueError("need max_distance_m > 0 and max_cost > 0")
        if self.max_distance_partial_m < self.max_distance_m:
            raise ValueError("need max_distance_partial_m >= max_distance_m")
        if min(self.weight_distance, self.weight_iou, self.weight_appearance) < 0:
            raise ValueError("cost weights must be >= 0")
        if not 0 < self.orb_ratio <= 1 or self.orb_max_distance < 0:
            raise ValueError("need 0 < orb_ratio <= 1 and orb_max_distance >= 0")


@dataclass(frozen=True, eq=False)
class KeyframeView:
    """One keyframe as the association sees it.

    Attributes:
        index: keyframe number in the associator (0, 1, 2, ... in arrival order).
        T_world_camera: (4, 4) camera pose in ``world``.
        camera: colour-camera intrinsics (the measurements' pixel boxes are in this image).
        measurements: the keyframe's object measurements.
        mids: associator-wide measurement ids, one per measurement.
    """

    index: int
    T_world_camera: F64
    camera: PinholeCamera
    measurements: tuple[ObjectMeasurement, ...]
    mids: tuple[int, ...]


@dataclass(eq=False)
class GroupLandmark:
    """A group-level landmark ``O^G_{n,i}``: one track of one keyframe group.

    Attributes:
        category: class of its measurements.
        mids: measurement ids, in keyframe order.
        measurements: the measurements, aligned with ``mids``.
        keyframes: keyframe index of each measurement (one measurement per keyframe).
    """

    category: str
    mids: list[int] = field(default_factory=list)
    measurements: list[ObjectMeasurement] = field(default_factory=list)
    keyframes: list[int] = field(default_factory=list)

    def add(self, mid: int, measurement: ObjectMeasurement, keyframe: int) -> None:
        self.mids.append(mid)
        self.measurements.append(measurement)
        self.keyframes.append(keyframe)

    @property
    def poses(self) -> F64:
        """(K, 4, 4) measurement poses in ``world``."""
        return np.stack([m.T_world_object for m in self.measurements])


def _orb_similarity(a: NDArray[np.uint8], b: NDArray[np.uint8], cfg: MotConfig) -> float | None:
    """Share of descriptors of the smaller set with a ratio-test match in the other; None if empty."""
    if len(a) == 0 or len(b) == 0:
        return None
    if len(a) > len(b):
        a, b = b, a
    if len(b) < 2:
        d = int(cv2.norm(a[0], b[0], cv2.NORM_HAMMING))
        return float(d <= cfg.orb_max_distance) if len(a) == 1 else None
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    good = 0
    for pair in matcher.knnMatch(a, b, k=2):
        if len(pair) == 2 and pair[0].distance <= cfg.orb_ratio * pair[1].distance \
                and pair[0].distance <= cfg.orb_max_distance:
            good += 1
    return good / len(a)


def appearance_similarity(
    a: ObjectMeasurement, b: ObjectMeasurement, config: MotConfig | None = None
) -> float:
    """Appearance similarity in [0, 1] of two measurements.

    Mean of the colour-histogram intersection ``sum(min(h_a, h_b))`` (L1-normalised
    histograms) and the ORB match ratio; the histogram alone when either has no
    descriptors or the histograms differ in length (then 0.5, "unknown").
    """
    cfg = config or MotConfig()
    if a.color_hist.shape == b.color_hist.shape and a.color_hist.size:
        hist = float(np.minimum(a.color_hist, b.color_hist).sum())
    else:
        hist = 0.5
    orb = _orb_similarity(a.descriptors, b.descriptors, cfg)
    return hist if orb is None else 0.5 * (hist + orb)


@dataclass(eq=False)
class _Track:
    landmark: GroupLandmark
    last: ObjectMeasurement
    last_partial: bool


def _cost(track: _Track, m: ObjectMeasurement, partial: bool, view: KeyframeView, cfg: MotConfig,
          class_extent: F64 | None) -> float:
    last = track.last
    if last.category != m.category:
        return _FORBIDDEN
    if cfg.track_reference == "mean":
        centre = np.mean([t[:3, 3] for t in track.landmark.poses], axis=0)
    else:
        centre = last.T_world_object[:3, 3]
    residual = (m.T_world_object[:3, 3] - centre)[None, None]
    if cfg.size_slack > 0:
        residual = partial_view_slack(residual, world_extents(m.T_world_object, m.size)[None],
                                      world_extents(last.T_world_object, last.size)[None], cfg.size_slack,
                                      class_extent)
    dist = float(np.linalg.norm(residual))
    gate = cfg.max_distance_partial_m if partial or track.last_partial else cfg.max_distance_m
    if dist > gate:
        return _FORBIDDEN
    box = project_box(last.T_world_object, last.size, view.T_world_camera, view.camera)
    iou = 0.0 if box is None else box_iou(box, m.box_xyxy)
    app = appearance_similarity(last, m, cfg) if cfg.weight_appearance > 0 else 1.0
    return (cfg.weight_distance * min(dist / cfg.max_distance_m, 1.0) + cfg.weight_iou * (1.0 - iou)
            + cfg.weight_appearance * (1.0 - app))


def track_group(
    keyframes: Sequence[KeyframeView],
    config: MotConfig | None = None,
    class_extent: Callable[[str], F64 | None] | None = None,
    completed_when_cut: Collection[str] = (),
) -> list[GroupLandmark]:
    """Track the measurements of one keyframe group into group-level landmarks.

    Args:
        keyframes: the group's keyframes in time order.
        config: cost weights and gates.
        class_extent: class name -> the largest world-axis extent (3,) of an object of the
            class, or None; the partial-view slack clips extents to it
            (:func:`~wardmap.server.association.geometry.partial_view_slack`).
        completed_when_cut: classes whose views touching the image border are gated as whole
            views (``AssociationConfig.completed_when_cut``: the perception completes them).

    Returns:
        One :class:`GroupLandmark` per track, ordered by first appearance; every
        measurement of the group is in exactly one of them, and no landmark holds two
        measurements of one keyframe.
    """
    cfg = config or MotConfig()
    tracks: list[_Track] = []
    for view in keyframes:
        n = len(view.measurements)
        partial = [m.category not in completed_when_cut
                   and is_truncated(m.box_xyxy, view.camera, cfg.border_px) for m in view.measurements]
        matched: dict[int, int] = {}
        if tracks and n:
            bounds = [None if class_extent is None else class_extent(m.category) for m in view.measurements]
            cost = np.array([[_cost(t, m, partial[c], view, cfg, bounds[c])
                              for c, m in enumerate(view.measurements)] for t in tracks])
            rows, cols = linear_sum_assignment(cost)
            for r, c in zip(rows.tolist(), cols.tolist(), strict=True):
                if cost[r, c] <= cfg.max_cost:
                    matched[c] = r
        for c, (mid, m) in enumerate(zip(view.mids, view.measurements, strict=True)):
            if c in matched:
                track = tracks[matched[c]]
                track.landmark.add(mid, m, view.index)
                track.last = m
                track.last_partial = partial[c]
            else:
                lm = GroupLandmark(m.category)
                lm.add(mid, m, view.index)
                tracks.append(_Track(lm, m, partial[c]))
    return [t.landmark for t in tracks]


