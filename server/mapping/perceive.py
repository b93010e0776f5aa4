"""One keyframe through perception, for whoever measures it: a perception worker
(``workers.py``) or the mapping stage itself (``stage.py``, when no worker has it).

:class:`KeyframeMeasurer` decodes a stored keyframe, runs the segmenter and measures every
non-``moving`` instance in 3D (``server/perception/keyframe.py``), and returns a
:class:`~wardmap.server.store.Perceived`: the measurements with the colour-camera pose they were
computed with (the keyframe's map-pose prior, or its odom pose), so the stage can move them to
wherever the back-end puts the keyframe later. A keyframe perception cannot measure (corrupt
image, no intrinsics, model error) is a result too, its ``failure`` the counted reason (the
error type), logged here with its message. Not thread safe (one segmenter): one per thread.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from typing import Final

import cv2

from wardmap.server.decoded import DecodedCache, decode_images
from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.perception.floor import LeftOut
from wardmap.server.perception.keyframe import keyframe_camera, keyframe_map_pose, measure_keyframe_msg
from wardmap.server.perception.models import Segmenter
from wardmap.server.store import MappedPose, Perceived
from wardmap.shared.errors import WardmapError, WireError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.wire import KeyframeMsg, decode_keyframe

log = logging.getLogger(__name__)

__all__ = ["MAPPING_CURSOR", "PERCEPTION_ERRORS", "KeyframeMeasurer", "Measured", "mapped_pose"]

MAPPING_CURSOR: Final = "mapping"
"""The mapping stage's cursor in the store: keyframes up to it are committed to the map's records
(perception workers claim only keyframes after it)."""

PERCEPTION_ERRORS = (WardmapError, WireError, cv2.error, ValueError)
"""Errors that mean "this keyframe cannot be measured" (skipped with the type as reason), not a bug."""


@dataclass(frozen=True, eq=False)
class Measured:
    """One keyframe through perception.

    Attributes:
        result: what is stored for the mapping stage.
        left_out: instances the floor checks left out (``floor.LeftOut``; zeros on a failure).
        skipped: instances measurement could not measure, by kind.
    """

    result: Perceived
    left_out: LeftOut = field(default_factory=lambda: LeftOut(0, 0, 0))
    skipped: Counter[str] = field(default_factory=Counter)


def mapped_pose(robot_id: str, session_id: str, seq: int, msg: KeyframeMsg | None) -> MappedPose:
    """The pose a processed keyframe's measurements were computed with (its map-pose prior, or
    its odom frame); none when it was not measured (undecodable, no intrinsics)."""
    if msg is None or msg.intrinsics is None:
        return MappedPose(robot_id, session_id, seq, None, None)
    return MappedPose(robot_id, session_id, seq, keyframe_map_pose(msg), keyframe_camera(msg))


class KeyframeMeasurer:
    """Measures stored keyframes with one segmenter (see the module docstring).

    Args:
        segmenter: a ready segmenter (not shared with another thread).
        config: perception settings (measurement, floor checks).
        knowledge: the knowledge graph whose ``moving`` classes are left out (the packaged one
            when None).
    """

    def __init__(self, segmenter: Segmenter, config: PerceptionConfig,
                 knowledge: KnowledgeGraph | None = None) -> None:
        kg = knowledge if knowledge is not None else KnowledgeGraph.load()
        self._segmenter = segmenter
        self._config = config
        self._moving = {c.name for c in kg.classes if str(c.mobility) == "moving"}

    def measure(self, key: str, payload: bytes, decoded: DecodedCache | None = None) -> Measured:
        """Measure keyframe ``key`` (``"<robot>/<session>/<seq>"``) from its stored ``payload``, or
        from ``decoded``'s entry for it when there is one (ingest of this process decoded it).

        Raises:
            Exception: only what is not a perception failure (:data:`PERCEPTION_ERRORS`): a bug.
        """
        robot_id, session_id, seq_text = key.split("/")
        seq = int(seq_text)
        try:
            if decoded is not None:
                entry = decoded.decoded(key, payload)
                msg, images = entry.msg, decoded.images(entry)
            else:
                msg = decode_keyframe(payload)
                images = decode_images(msg)
            report = measure_keyframe_msg(msg, key, segmenter=self._segmenter, config=self._config,
                                          moving=self._moving, images=images)
        except PERCEPTION_ERRORS as exc:
            log.warning("keyframe %s: perception skipped: %s: %s", key, type(exc).__name__, exc)
            return Measured(Perceived(MappedPose(robot_id, session_id, seq, None, None), False, [],
                                      type(exc).__name__))
        left = report.left_out
        if any(left):
            log.debug("keyframe %s: %d instance(s) float above the floor, %d lie on a taller surface, "
                      "%d lie flat on the floor; left out", key, *left)
        result = Perceived(mapped_pose(robot_id, session_id, seq, msg), msg.T_map_odom is not None,
                           list(report.measurements))
        return Measured(result, left, Counter(skip.kind for skip in report.skipped))
