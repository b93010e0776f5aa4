"""Row conversions and argument checks every map store backend shares (no SQL dialect here).

Columns are listed in the order the backends' ``SELECT`` statements read them
(:data:`OBJECT_COLUMNS`, :data:`OBS_COLUMNS`, :data:`TOKEN_COLUMNS`); parameters are dicts
or tuples of plain Python values (floats, ints, str, bytes) that both ``sqlite3`` and psycopg
bind. Poses are 16 little-endian float64, row-major (``codec.pose_blob``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Final

import numpy as np

from wardmap.server.store import schema
from wardmap.server.store.codec import camera_to_json, pose_blob, pose_from_blob
from wardmap.server.store.records import (
    MAX_PAGE,
    MAX_REASON_LEN,
    MappedPose,
    ObjectRecord,
    ObjectRow,
    Observation,
    ObservationRecord,
    StoreDamagedError,
    StoreError,
    TokenRecord,
    Vec3,
)
from wardmap.server.store.schema import Dialect
from wardmap.shared.wire import KeyframeMsg


def insert_args(
    msg: object, payload: object, received_s: object
) -> tuple[tuple[str, str, int], bytes, float]:
    """Check :meth:`~wardmap.server.store.protocol.KeyframeStore.insert`'s arguments; returns
    ``(key, payload bytes, received_s)``; StoreError names a bad one."""
    if not isinstance(msg, KeyframeMsg):
        raise StoreError(f"msg must be a KeyframeMsg, got {type(msg).__name__}")
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise StoreError(f"payload must be bytes, got {type(payload).__name__}")
    data = bytes(payload)
    if not data:
        raise StoreError("payload is empty")
    t = check_seconds(received_s, "received_s")
    return (msg.robot_id, msg.session_id, int(msg.seq)), data, t


def check_reason(reason: object, n: object) -> None:
    """Check :meth:`~wardmap.server.store.protocol.KeyframeStore.count_rejection`'s arguments."""
    if not isinstance(reason, str) or not 0 < len(reason) <= MAX_REASON_LEN:
        raise StoreError(f"reason must be a str of 1-{MAX_REASON_LEN} characters, got {reason!r:.80}")
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n < 2**62:
        raise StoreError(f"n must be an int >= 1, got {n!r:.40}")


def check_limit(limit: object) -> int:
    """A page size of :meth:`~wardmap.server.store.protocol.KeyframeStore.keyframes`."""
    if isinstance(limit, bool) or not isinstance(limit, int) or not 1 <= limit <= MAX_PAGE:
        raise StoreError(f"limit must be an int in [1, {MAX_PAGE}], got {limit!r}")
    return limit


def check_cursor(after: tuple[object, ...]) -> tuple[str, int]:
    """A ``(session_id, seq)`` page cursor."""
    if len(after) != 2 or not isinstance(after[0], str):
        raise StoreError(f"cursor must be (session_id, seq) or a stamp, got {after!r:.80}")
    return after[0], check_seq(after[1])


TOKEN_COLUMNS: Final = "token_id, name, scope, secret_sha256, created_s, revoked_s"


def token_from_row(r: Sequence[Any]) -> TokenRecord:
    scope = str(r[2])
    if scope not in ("read", "admin"):  # the table's CHECK forbids it: only a hand-edited file
        raise StoreDamagedError(f"token {r[0]!r} has an unknown scope {scope!r}")
    return TokenRecord(str(r[0]), str(r[1]), "admin" if scope == "admin" else "read", bytes(r[3]),
                       float(r[4]), None if r[5] is None else float(r[5]))



def check_str(value: object, field: str) -> str:
    if not isinstance(value, str) or not value:
        raise StoreError(f"{field} must be a non-empty str, got {value!r:.80}")
    return value


def check_seq(value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < 2**63:
        raise StoreError(f"seq must be an int in [0, 2**63), got {value!r:.80}")
    return value


def check_seconds(value: object, field: str, *, positive: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise StoreError(f"{field} must be a number of seconds, got {value!r:.80}")
    v = float(value)
    if not math.isfinite(v) or (positive and v <= 0):
        raise StoreError(f"{field} must be a finite{' positive' if positive else ''} number, got {v}")
    return v


OBJECT_COLUMNS: Final = (
    "o.object_id, o.category, o.confidence, o.T_world_object, o.x, o.y, o.z, o.yaw, "
    "o.qx, o.qy, o.qz, o.qw, o.size_x, o.size_y, o.size_z, "
    "o.min_x, o.min_y, o.min_z, o.max_x, o.max_y, o.max_z, "
    "o.color_r, o.color_g, o.color_b, o.n_observations, o.first_seen_s, o.last_seen_s, o.confirmed"
)
COMPACT_COLUMNS: Final = "o.object_id, o.category, o.x, o.y, o.z, o.yaw, o.size_x, o.size_y, o.size_z"
"""The columns of a :class:`~wardmap.server.store.records.CompactRow`, in its order."""
OBS_COLUMNS: Final = (
    "observation_id, added_s, object_id, robot_id, session_id, seq, stamp, category, confidence, "
    "box_x1, box_y1, box_x2, box_y2, T_world_object, size_x, size_y, size_z"
)

def object_params(o: ObjectRow, now_s: float) -> dict[str, Any]:
    T = o.T_world_object
    row: dict[str, Any] = {
        "object_id": o.object_id, "category": o.category, "confidence": o.confidence,
        "T": pose_blob(T), "x": T[0, 3], "y": T[1, 3], "z": T[2, 3], "yaw": o.yaw,
        "qx": o.q_xyzw[0], "qy": o.q_xyzw[1], "qz": o.q_xyzw[2], "qw": o.q_xyzw[3],
        "size_x": o.size[0], "size_y": o.size[1], "size_z": o.size[2],
        "min_x": o.bounds_min[0], "min_y": o.bounds_min[1], "min_z": o.bounds_min[2],
        "max_x": o.bounds_max[0], "max_y": o.bounds_max[1], "max_z": o.bounds_max[2],
        "color_r": None, "color_g": None, "color_b": None, "confirmed": int(o.confirmed), "now": now_s,
    }
    if o.color_rgb is not None:
        row.update(color_r=o.color_rgb[0], color_g=o.color_rgb[1], color_b=o.color_rgb[2])
    return {k: float(v) if isinstance(v, np.floating) else v for k, v in row.items()}


def observation_params(obs: Observation, now_s: float) -> dict[str, Any]:
    box, size = obs.box_xyxy, obs.size
    return {
        "object_id": obs.object_id, "robot_id": obs.robot_id, "session_id": obs.session_id,
        "seq": int(obs.seq), "stamp": float(obs.stamp), "category": obs.category,
        "confidence": float(obs.confidence),
        "box_x1": float(box[0]), "box_y1": float(box[1]), "box_x2": float(box[2]), "box_y2": float(box[3]),
        "T": pose_blob(obs.T_world_object),
        "size_x": float(size[0]), "size_y": float(size[1]), "size_z": float(size[2]), "now": now_s,
    }


def mapped_params(p: MappedPose) -> tuple[str, str, int, bytes | None, str | None]:
    if p.T_map_camera is None or p.camera is None:
        return p.robot_id, p.session_id, p.seq, None, None
    return p.robot_id, p.session_id, p.seq, pose_blob(p.T_map_camera), camera_to_json(p.camera)



def object_record(r: Sequence[Any], robots: tuple[str, ...]) -> ObjectRecord:
    color = None if r[21] is None else (float(r[21]), float(r[22]), float(r[23]))
    return ObjectRecord(
        object_id=int(r[0]), category=str(r[1]), confidence=float(r[2]), T_world_object=pose_from_blob(r[3]),
        position=(float(r[4]), float(r[5]), float(r[6])), yaw=float(r[7]),
        q_xyzw=(float(r[8]), float(r[9]), float(r[10]), float(r[11])),
        size=(float(r[12]), float(r[13]), float(r[14])),
        bounds_min=(float(r[15]), float(r[16]), float(r[17])),
        bounds_max=(float(r[18]), float(r[19]), float(r[20])),
        color_rgb=color, n_observations=int(r[24]), first_seen_s=float(r[25]), last_seen_s=float(r[26]),
        robots=robots, confirmed=bool(r[27]),
    )


def observation_record(r: Sequence[Any]) -> ObservationRecord:
    return ObservationRecord(
        observation_id=int(r[0]), added_s=float(r[1]), object_id=int(r[2]), robot_id=str(r[3]),
        session_id=str(r[4]), seq=int(r[5]), stamp=float(r[6]), category=str(r[7]), confidence=float(r[8]),
        box_xyxy=np.array([r[9], r[10], r[11], r[12]], dtype=np.float64),
        T_world_object=pose_from_blob(r[13]),
        size=np.array([r[14], r[15], r[16]], dtype=np.float64),
    )


def find_sql(
    dialect: Dialect,
    *,
    category: str | None,
    near: Vec3 | None,
    radius_m: float | None,
    min_confidence: float | None,
    robot: str | None,
    include_unconfirmed: bool,
    limit: int,
    offset: int,
    columns: str = OBJECT_COLUMNS,
) -> tuple[str, dict[str, Any]]:
    """The SELECT (and its parameters, ``:name`` placeholders) a store's ``find_objects`` runs:
    up to ``limit + 1`` rows of ``columns`` (:data:`OBJECT_COLUMNS`; ``find_compact``:
    :data:`COMPACT_COLUMNS`), then the squared distance to ``near`` when given.

    With ``radius_m`` the dialect's spatial index selects candidates whose bounds meet the cube
    of half-side ``radius_m`` around ``near`` (SQLite: the R*Tree; PostgreSQL: the GiST index
    over the bounds' xy box, then z; PostGIS: the n-D GiST index over the 3D bounds); the exact
    centre distance then decides.
    """
    where: list[str] = []
    params: dict[str, Any] = {"limit": limit + 1, "offset": offset}
    source = "objects AS o"
    select = columns
    order = "o.object_id"
    if near is not None:
        params.update(px=near[0], py=near[1], pz=near[2])
        d2 = "((o.x - :px) * (o.x - :px) + (o.y - :py) * (o.y - :py) + (o.z - :pz) * (o.z - :pz))"
        select += f", {d2} AS d2"
        order = "d2, o.object_id"
        if radius_m is not None:
            r = float(radius_m)
            if dialect == "sqlite":
                # CROSS JOIN: the R*Tree drives the loop (SQLite keeps the left table outermost).
                source = "objects_rtree AS r CROSS JOIN objects AS o ON o.object_id = r.object_id"
                where += [
                    "r.max_x >= :lo_x", "r.min_x <= :hi_x", "r.max_y >= :lo_y", "r.min_y <= :hi_y",
                    "r.max_z >= :lo_z", "r.min_z <= :hi_z",
                ]
            elif dialect == "postgis":  # the indexed expression (schema.POSTGIS_BOUNDS), verbatim
                where.append(f"{schema.POSTGIS_BOUNDS} &&& ST_MakeLine(ST_MakePoint(:lo_x, :lo_y, :lo_z), "
                             "ST_MakePoint(:hi_x, :hi_y, :hi_z))")
            else:
                where += [
                    "box(point(o.min_x, o.min_y), point(o.max_x, o.max_y)) && "
                    "box(point(:lo_x, :lo_y), point(:hi_x, :hi_y))",
                    "o.max_z >= :lo_z", "o.min_z <= :hi_z",
                ]
            where.append(f"{d2} <= :r2")
            params.update(
                lo_x=near[0] - r, hi_x=near[0] + r, lo_y=near[1] - r, hi_y=near[1] + r,
                lo_z=near[2] - r, hi_z=near[2] + r, r2=r * r,
            )
    if category is not None:
        where.append("o.category = :category")
        params["category"] = category
    if not include_unconfirmed:
        where.append("o.confirmed = 1")
    if min_confidence is not None:
        where.append("o.confidence >= :min_confidence")
        params["min_confidence"] = float(min_confidence)
    if robot is not None:
        where.append(
            "EXISTS (SELECT 1 FROM object_robots AS ro WHERE ro.object_id = o.object_id "
            "AND ro.robot_id = :robot)"
        )
        params["robot"] = robot
    sql = f"SELECT {select} FROM {source}"
    if where:
        sql += " WHERE " + " AND ".join(where)
    sql += f" ORDER BY {order} LIMIT :limit OFFSET :offset"
    return sql, params
