"""The robot's side of the server's corrections: which ``T_map_odom`` holds for the running session.

The map server publishes a :class:`~wardmap.shared.robotwire.CorrectionMsg` on the robot's key
``wardmap/v1/robots/<robot_id>/correction`` when it anchors a session on the shared map and each
time it moves it (docs/wire.md, ``wardmap.correction``). :class:`Corrections` is the one owner of
what this robot has made of them (in the edge agent: the sender thread, which receives them). It
decodes each payload and keeps the newest valid correction of the running session; anything else
is refused and counted under a reason of :data:`REJECT_REASONS`, never raised:

- ``undecodable``: not a valid ``wardmap.correction`` (any :class:`~wardmap.shared.errors.WireError`);
- ``other_robot``: for another robot id;
- ``other_session``: for another session of this robot (the key is per robot, so the server's
  corrections of this robot's earlier sessions arrive here too);
- ``stale``: a lower revision than the one held, or the same revision with another content.

The same correction arriving twice (the subscription and a query both deliver it) is applied once
and counted in ``duplicates``, not refused.

Map poses: ``T_map_x = T_map_odom @ T_odom_x`` (docs/ARCHITECTURE.md, "Frames"), with the held
correction's ``T_map_odom``, or else the prior the robot was started with (``--map-pose``), if
any. The correction never goes back to the server: keyframes carry only that prior.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from typing import Final, Literal, TypeAlias, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.shared.errors import WireError
from wardmap.shared.robotwire import CorrectionMsg, decode_correction
from wardmap.shared.se3 import check_transform
from wardmap.shared.zenoh_config import validate_robot_id

log = logging.getLogger(__name__)

__all__ = ["REJECT_REASONS", "Corrections", "RejectReason"]

F64 = NDArray[np.float64]

RejectReason: TypeAlias = Literal["undecodable", "other_robot", "other_session", "stale"]
REJECT_REASONS: Final[tuple[str, ...]] = get_args(RejectReason)
"""Why a correction payload was refused; the fixed vocabulary of :meth:`Corrections.rejections`."""


class Corrections:
    """The corrections one robot received: the running session's current ``T_map_odom``.

    Not thread-safe: one thread owns it (the edge agent's sender); others read it only after that
    thread has stopped.
    """

    def __init__(self, robot_id: str, *, T_map_odom_prior: ArrayLike | None = None) -> None:
        """
        Args:
            robot_id: this robot (corrections for another are refused).
            T_map_odom_prior: (4, 4) the session's odom frame on the map when the robot was started
                at a known map pose (``wardmap edge --map-pose``); map poses use it until a
                correction arrives. None: no map pose before the first correction.
        """
        self.robot_id = validate_robot_id(robot_id)
        self._prior: F64 | None = None
        if T_map_odom_prior is not None:
            self._prior = check_transform(np.asarray(T_map_odom_prior, np.float64), "T_map_odom_prior").copy()
            self._prior.flags.writeable = False
        self._current: CorrectionMsg | None = None
        self._applied = 0
        self._duplicates = 0
        self._rejected: Counter[str] = Counter()

    # ------------------------------------------------------------------ input

    def handle(self, payload: bytes, session_id: str) -> bool:
        """Decode a correction payload and apply it if it is news for session ``session_id``.

        Args:
            payload: bytes as received on the robot's correction key (untrusted).
            session_id: the running session of this robot.

        Returns:
            True if applied (it is now :attr:`current`); False if refused (counted under its
            reason) or a duplicate of the held one. Never raises for any payload.
        """
        try:
            msg = decode_correction(payload)
        except WireError as exc:
            return self._reject("undecodable", f"{exc}")
        if msg.robot_id != self.robot_id:
            return self._reject("other_robot", f"robot {msg.robot_id!r}")
        if msg.session_id != session_id:
            return self._reject("other_session", f"session {msg.session_id!r}, running {session_id!r}")
        held = self._current
        if held is not None and held.session_id == msg.session_id:
            if msg.revision == held.revision and _same(msg, held):
                self._duplicates += 1
                return False
            if msg.revision <= held.revision:
                return self._reject("stale", f"revision {msg.revision}, holding {held.revision}")
        self._current = msg
        self._applied += 1
        t = msg.T_map_odom[:3, 3]
        log.info("correction %d of session %s applied: %s, T_map_odom t = (%.3f, %.3f, %.3f) m%s",
                 msg.revision, session_id, msg.state, *t,
                 f", anchored to {msg.anchored_to}" if msg.anchored_to else "")
        return True

    def _reject(self, reason: RejectReason, detail: str) -> bool:
        first = not self._rejected[reason]
        self._rejected[reason] += 1
        # Warn on the first of each reason; a flood of bad messages must not flood the log.
        level = logging.WARNING if first else logging.DEBUG
        log.log(level, "correction refused (%s): %s", reason, detail[:300])
        return False

    # ------------------------------------------------------------------ state

    @property
    def current(self) -> CorrectionMsg | None:
        """The correction applied last (of the running session), or None."""
        return self._current

    @property
    def anchored(self) -> bool:
        """A correction of the running session was applied (the server anchored it)."""
        return self._current is not None

    @property
    def T_map_odom(self) -> F64 | None:
        """(4, 4) the running session's odom frame on the map: the correction's, else the prior,
        else None. Read-only."""
        if self._current is not None:
            return self._current.T_map_odom
        return self._prior

    def map_pose(self, T_odom_x: ArrayLike) -> F64 | None:
        """``T_map_x = T_map_odom @ T_odom_x`` for a pose in the session's odom frame (the base's
        or the camera's), or None while no ``T_map_odom`` is known."""
        T = self.T_map_odom
        if T is None:
            return None
        out: F64 = T @ np.asarray(T_odom_x, np.float64)
        return out

    def rejections(self) -> dict[str, int]:
        """Refused payloads by reason (:data:`REJECT_REASONS`), only reasons that occurred."""
        return {r: self._rejected[r] for r in REJECT_REASONS if self._rejected[r]}

    def stats(self, *, T_odom_base: ArrayLike | None = None,
              T_odom_camera: ArrayLike | None = None) -> dict[str, int | float]:
        """Flat numbers for the heartbeat.

        ``anchored`` (0/1), ``corrections`` (applied), ``bad_corrections`` (refused, all reasons),
        and, when a map pose is known, ``map_x``, ``map_y``, ``map_z`` (m) and ``map_yaw_deg`` of
        the base (``T_odom_base``; heading of its x axis about the map's z) or, without one, of the
        camera (``T_odom_camera``; heading of its optical z axis).
        """
        out: dict[str, int | float] = {
            "anchored": int(self.anchored),
            "corrections": self._applied,
            "bad_corrections": sum(self._rejected.values()),
        }
        pose = self.map_heading(T_odom_base=T_odom_base, T_odom_camera=T_odom_camera)
        if pose is not None:
            out.update(zip(("map_x", "map_y", "map_z", "map_yaw_deg"), pose, strict=True))
        return out

    def map_heading(self, *, T_odom_base: ArrayLike | None = None,
                    T_odom_camera: ArrayLike | None = None) -> tuple[float, float, float, float] | None:
        """``(x, y, z, yaw_deg)`` on the map of the base (x axis forward), else of the camera
        (z axis forward), rounded to 1 mm and 0.01 deg; None without a map pose or a pose."""
        if T_odom_base is not None:
            T, forward = self.map_pose(T_odom_base), 0
        elif T_odom_camera is not None:
            T, forward = self.map_pose(T_odom_camera), 2
        else:
            return None
        if T is None:
            return None
        yaw = math.degrees(math.atan2(float(T[1, forward]), float(T[0, forward])))
        x, y, z = (round(float(v), 3) for v in T[:3, 3])
        return x, y, z, round(yaw, 2)

    def summary(self, *, T_odom_base: ArrayLike | None = None,
                T_odom_camera: ArrayLike | None = None) -> dict[str, object]:
        """JSON-able totals for the agent's run summary: ``anchored`` (bool),
        ``correction_revision`` and ``anchored_to`` of the held correction (None without one),
        ``corrections`` (applied), ``duplicate_corrections``, ``bad_corrections`` (refusals by
        reason) and ``map_pose`` (``{"x", "y", "z", "yaw_deg"}`` as in :meth:`stats`, or None)."""
        cur = self._current
        heading = self.map_heading(T_odom_base=T_odom_base, T_odom_camera=T_odom_camera)
        map_pose = None if heading is None else dict(zip(("x", "y", "z", "yaw_deg"), heading, strict=True))
        return {
            "anchored": self.anchored,
            "correction_revision": None if cur is None else cur.revision,
            "anchored_to": None if cur is None else cur.anchored_to,
            "corrections": self._applied,
            "duplicate_corrections": self._duplicates,
            "bad_corrections": self.rejections(),
            "map_pose": map_pose,
        }


def _same(a: CorrectionMsg, b: CorrectionMsg) -> bool:
    return (a.stamp, a.state, a.anchored_to) == (b.stamp, b.state, b.anchored_to) and bool(
        np.array_equal(a.T_map_odom, b.T_map_odom))
