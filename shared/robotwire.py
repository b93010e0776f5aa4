"""What the map server tells one robot: its session's correction (schema ``wardmap.correction``).

When the server's back-end anchors a robot session on the shared map (a verified loop closure
solves the session's ``T_map_odom``), and every time the pose graph later moves it, the server
publishes a :class:`CorrectionMsg` on :func:`~wardmap.shared.zenoh_config.correction_key`
(``wardmap/v1/robots/<robot_id>/correction``, the server-owned subtree of that robot) and
answers queries there with the latest one (``server/corrections.py``). The robot applies it to
its odometry-frame poses (``edge/corrections.py``): ``T_map_base = T_map_odom @ T_odom_base``.

The message follows the rules of the keyframe schema (``shared/wire.py``, docs/wire.md): one
msgpack map with ``schema`` and ``version``, poses in the wire's pose form, a frozen dataclass
that validates on construction, and one encode/decode pair; :func:`decode_correction` is the
boundary for untrusted bytes and raises only :class:`~wardmap.shared.errors.WireError`, whose
``field`` is the dotted wire name of the bad field (``T_map_odom.q_xyzw``; ``""`` for the
payload as a whole).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Final, Literal, TypeAlias, get_args

import msgpack
import numpy as np
from numpy.typing import NDArray

from wardmap.shared.errors import GeometryError, WireError
from wardmap.shared.wire import (
    SCHEMA_VERSION,
    Fields,
    check_float,
    check_id,
    check_int,
    check_pose,
    pose_from_wire,
    pose_to_wire,
    unpack_payload,
)

__all__ = [
    "CORRECTION_STATES",
    "ENCODING",
    "MAX_CORRECTION_BYTES",
    "SCHEMA_CORRECTION",
    "CorrectionMsg",
    "CorrectionState",
    "decode_correction",
    "encode_correction",
]

SCHEMA_CORRECTION: Final = "wardmap.correction"
ENCODING: Final = "application/msgpack"
"""Zenoh encoding the server declares for correction payloads."""
MAX_CORRECTION_BYTES: Final = 4096
"""Largest correction payload :func:`decode_correction` accepts (an encoded one is ~250 bytes)."""
MAX_REVISION: Final = 2**63

CorrectionState: TypeAlias = Literal["anchored"]
"""How the server holds the session: ``anchored`` = on the shared map, ``T_map_odom`` solved.
More states may come within version 1 (a robot that does not know one refuses the message)."""
CORRECTION_STATES: Final[tuple[str, ...]] = get_args(CorrectionState)


@dataclass(frozen=True, eq=False)
class CorrectionMsg:
    """The server's latest estimate of one robot session's place on the map.

    Attributes:
        robot_id: the robot, 1-64 characters ``[A-Za-z0-9_.-]``.
        session_id: the robot's mapping session whose ``odom`` frame is corrected, same rule.
        revision: 0 <= revision < 2**63; increases with each new correction of the session
            (a robot keeps the highest it has seen and refuses lower ones).
        stamp: when the server made it, seconds since the Unix epoch (> 0).
        T_map_odom: (4, 4) float64, the session's odom frame in the shared map frame
            (``p_map = T_map_odom @ p_odom``). Stored read-only.
        state: ``anchored`` (the only state of version 1).
        anchored_to: ``"<robot_id>/<session_id>"`` of the map session the anchoring closure
            reached, or None.
    """

    robot_id: str
    session_id: str
    revision: int
    stamp: float
    T_map_odom: NDArray[np.float64]
    state: CorrectionState = "anchored"
    anchored_to: str | None = None

    def __post_init__(self) -> None:
        check_id(self.robot_id, "robot_id")
        check_id(self.session_id, "session_id")
        check_int(self.revision, "revision", 0, MAX_REVISION)
        object.__setattr__(self, "revision", int(self.revision))
        object.__setattr__(self, "stamp", check_float(self.stamp, "stamp", positive=True))
        object.__setattr__(self, "T_map_odom", check_pose(self.T_map_odom, "T_map_odom"))
        if not isinstance(self.state, str) or self.state not in CORRECTION_STATES:
            raise WireError("state", f"unknown state {self.state!r:.40}; expected one of {CORRECTION_STATES}")
        if self.anchored_to is not None:
            _check_session_ref(self.anchored_to, "anchored_to")


def _check_session_ref(value: object, field: str) -> str:
    """``"<robot_id>/<session_id>"``, both ids by the wire's id rule."""
    if not isinstance(value, str):
        raise WireError(field, f"expected a string, got {type(value).__name__}")
    parts = value.split("/")
    if len(parts) != 2:
        raise WireError(field, f"expected '<robot_id>/<session_id>', got {value[:140]!r}")
    check_id(parts[0], field)
    check_id(parts[1], field)
    return value


def _to_wire(msg: CorrectionMsg) -> dict[str, Any]:
    d: dict[str, Any] = {
        "schema": SCHEMA_CORRECTION, "version": SCHEMA_VERSION,
        "robot_id": msg.robot_id, "session_id": msg.session_id, "revision": msg.revision,
        "stamp": msg.stamp, "T_map_odom": pose_to_wire(msg.T_map_odom), "state": msg.state,
    }
    if msg.anchored_to is not None:
        d["anchored_to"] = msg.anchored_to
    return d


def encode_correction(msg: CorrectionMsg) -> bytes:
    """msgpack bytes of ``msg`` (schema ``wardmap.correction``, version 1).

    Raises:
        WireError: ``msg`` is not a :class:`CorrectionMsg`.
    """
    if not isinstance(msg, CorrectionMsg):
        raise WireError("", f"cannot encode {type(msg).__name__} as {SCHEMA_CORRECTION}")
    payload: bytes = msgpack.packb(_to_wire(msg), use_bin_type=True)
    return payload


def _correction_from_wire(f: Fields) -> CorrectionMsg:
    robot_id = check_id(f.get("robot_id"), "robot_id")
    session_id = check_id(f.get("session_id"), "session_id")
    revision = check_int(f.get("revision"), "revision", 0, MAX_REVISION)
    stamp = check_float(f.get("stamp"), "stamp", positive=True)
    T_map_odom = pose_from_wire(f.get("T_map_odom"), "T_map_odom")
    state = f.get("state")
    if not isinstance(state, str) or state not in CORRECTION_STATES:
        raise WireError("state", f"unknown state {state!r:.40}; expected one of {CORRECTION_STATES}")
    raw_ref = f.optional("anchored_to")
    anchored_to = None if raw_ref is None else _check_session_ref(raw_ref, "anchored_to")
    f.done()
    return CorrectionMsg(robot_id, session_id, revision, stamp, T_map_odom,
                         state, anchored_to)  # type: ignore[arg-type]  # state checked above


def decode_correction(payload: bytes, *, max_bytes: int = MAX_CORRECTION_BYTES) -> CorrectionMsg:
    """Parse and validate one correction from untrusted bytes.

    Args:
        payload: msgpack bytes as produced by :func:`encode_correction`.
        max_bytes: refuse larger payloads before unpacking anything.

    Raises:
        WireError: for any malformed input -- oversize, truncated or non-msgpack bytes, another
            ``schema``, an unknown ``version``, a missing, unknown, mistyped, non-finite or
            out-of-range field. ``.field`` names the field (``""``: the payload as a whole).
    """
    f = Fields(unpack_payload(payload, max_bytes=max_bytes), "")
    schema = f.get("schema")
    if schema != SCHEMA_CORRECTION:
        raise WireError("schema", f"expected {SCHEMA_CORRECTION}, got {schema!r:.60}")
    version = f.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version != SCHEMA_VERSION:
        raise WireError("version", f"unsupported version {version!r:.40} of {SCHEMA_CORRECTION}; this "
                                   f"build reads {SCHEMA_VERSION}")
    try:
        return _correction_from_wire(f)
    except WireError:
        raise
    except (ValueError, TypeError, KeyError, IndexError, OverflowError, ArithmeticError,
            GeometryError) as exc:  # safety net: validators raise WireError themselves
        raise WireError("", f"malformed {SCHEMA_CORRECTION}: {type(exc).__name__}: {exc}"[:300]) from exc
