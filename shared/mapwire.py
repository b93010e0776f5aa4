"""The object map's messages: one object shape for REST and Zenoh, and the Zenoh map schemas.

The map server answers queries on :data:`OBJECTS_KEY` and publishes changes on
:data:`UPDATES_KEY` (``server/mapserve.py``); its REST API (``GET /v1/objects``) sends the
same object. A robot (``edge/``) or any other client decodes the Zenoh messages with
:func:`decode_map_message`. Both sides import this module, so the format has one definition
(edge and server never import each other).

Messages are frozen dataclasses that validate on construction (a message that exists is
valid), as in ``shared/wire.py``; :func:`encode_map_message` / :func:`decode_map_message`
are the one encode/decode pair, and every bad field raises
:class:`~wardmap.shared.errors.WireError` naming it (``objects[2].confidence``).
Payloads are msgpack maps with ``schema`` and ``version``:

- ``wardmap.map.objects`` (:class:`ObjectsReply`): ``objects`` (list of object maps),
  ``next_offset`` (int or nil);
- ``wardmap.map.update`` (:class:`MapUpdate`): ``kind`` (``created``, ``updated``,
  ``deleted``), ``object``, ``merged_into`` (int, or nil unless a merge);
- ``wardmap.map.error`` (:class:`MapError`): ``detail``.

An object map (:class:`MapObject`, :func:`object_to_wire`) carries ``object_id``,
``category``, ``confidence``, the pose both as ``T_world_object`` (``{"t": [x, y, z],
"q_xyzw": [...]}``, the pose form of ``shared/wire.py``) and flat as ``position`` and
``q_xyzw`` (what REST clients always read), ``yaw`` (rad), ``size``, ``bounds_min``,
``bounds_max`` (metres), ``color_rgb`` (nil when unknown), ``n_observations``,
``first_seen_s``, ``last_seen_s``, ``robots``, ``confirmed`` (bool) and ``distance_m``
(nil unless the query had ``near``). docs/map_api.md has the full field list.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Final, Literal, TypeAlias, get_args

import msgpack
import numpy as np
from numpy.typing import NDArray

from wardmap.shared.errors import WireError
from wardmap.shared.se3 import make_transform, quat_to_rotation
from wardmap.shared.wire import QUAT_NORM_TOL, _check_float, _check_int, _check_text, _Fields
from wardmap.shared.zenoh_config import MAP_OBJECTS_KEY, MAP_UPDATES_KEY

__all__ = [
    "CHANGE_KINDS",
    "ENCODING",
    "MAX_DETAIL_LEN",
    "MAX_MESSAGE_BYTES",
    "OBJECTS_KEY",
    "SCHEMA_ERROR",
    "SCHEMA_OBJECTS",
    "SCHEMA_UPDATE",
    "UPDATES_KEY",
    "VERSION",
    "ChangeKind",
    "MapError",
    "MapMessage",
    "MapObject",
    "MapUpdate",
    "ObjectsReply",
    "decode_map_message",
    "encode_map_message",
    "object_from_wire",
    "object_to_wire",
]

OBJECTS_KEY: Final = MAP_OBJECTS_KEY
UPDATES_KEY: Final = MAP_UPDATES_KEY
SCHEMA_OBJECTS: Final = "wardmap.map.objects"
SCHEMA_UPDATE: Final = "wardmap.map.update"
SCHEMA_ERROR: Final = "wardmap.map.error"
SCHEMAS: Final = (SCHEMA_OBJECTS, SCHEMA_UPDATE, SCHEMA_ERROR)
VERSION: Final = 1
ENCODING: Final = "application/msgpack"
MAX_MESSAGE_BYTES: Final = 16 * 2**20
MAX_DETAIL_LEN: Final = 4096
"""Longest ``detail`` of an error reply, in characters."""

ChangeKind: TypeAlias = Literal["created", "updated", "deleted"]
CHANGE_KINDS: Final[tuple[str, ...]] = get_args(ChangeKind)

Vec3: TypeAlias = tuple[float, float, float]
Vec4: TypeAlias = tuple[float, float, float, float]
_INT64: Final = 2**63
_FMAX: Final = sys.float_info.max


# --------------------------------------------------------------------------- field checks
# The field readers of wire schema v1 (shared/wire.py), so both schemas validate alike.


def _float(value: object, field: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    """``value`` as a finite float in ``[lo, hi]`` (ints accepted, bools not)."""
    if type(value) is float and lo <= value <= hi and math.isfinite(value):
        return value  # the common case, checked cheaply: the list route builds 1000s of objects
    v = _check_float(value, field)
    if not lo <= v <= hi:
        raise WireError(field, f"expected a number in [{lo}, {hi}], got {v}")
    return v


def _int(value: object, field: str, lo: int) -> int:
    """``value`` as an int in ``[lo, 2**63)``; bools are not ints here."""
    if type(value) is int and lo <= value < _INT64:
        return value  # the common case, checked cheaply
    return _check_int(value, field, lo, _INT64)


def _name(value: object, field: str, max_len: int) -> str:
    """A non-empty string of at most ``max_len`` characters."""
    if type(value) is str and 0 < len(value) <= max_len:
        return value  # the common case, checked cheaply
    if not _check_text(value, field, max_len):
        raise WireError(field, "expected a non-empty string")
    return str(value)


def _vec(value: object, field: str, n: int, lo: float = -_FMAX) -> tuple[float, ...]:
    """``value`` as a tuple of ``n`` finite floats, each >= ``lo``."""
    if type(value) is tuple and len(value) == n:  # the common case (the map's records), checked cheaply
        for v in value:
            if type(v) is not float or not lo <= v <= _FMAX:  # NaN and infinities fail the comparison
                break
        else:
            return value
    if not isinstance(value, list | tuple | np.ndarray) or len(value) != n:
        raise WireError(field, f"expected a list of {n} numbers")
    return tuple(_float(v, f"{field}[{i}]", lo) for i, v in enumerate(value))


def _check_quat(q: tuple[float, ...], field: str) -> tuple[float, ...]:
    """``q`` unchanged if its norm is within ``QUAT_NORM_TOL`` of 1, the pose rule of
    ``shared/wire.py`` (it is not renormalised, so REST clients read the stored values exactly)."""
    x, y, z, w = q
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise WireError(field, f"quaternion norm {norm:.6g} is not within {QUAT_NORM_TOL} of 1")
    return q


def _robots(value: object, field: str) -> tuple[str, ...]:
    if type(value) is tuple:
        for r in value:
            if type(r) is not str or not 0 < len(r) <= 64:
                break
        else:
            return value  # the common case, checked cheaply
    if not isinstance(value, list | tuple):
        raise WireError(field, f"expected a list of robot ids, got {type(value).__name__}")
    return tuple(_name(r, f"{field}[{i}]", 64) for i, r in enumerate(value))


def _bool(value: object, field: str) -> bool:
    if not isinstance(value, bool):
        raise WireError(field, f"expected a bool, got {type(value).__name__}")
    return value


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class MapObject:
    """One object of the map as REST and Zenoh send it (world frame, metres, radians).

    Attributes:
        object_id: the map's id, >= 1.
        category: knowledge-graph class (``door``, ``bed``, ...).
        confidence: in [0, 1].
        position: centre of the object's box in the world frame ``(x, y, z)``, metres: the
            translation of ``T_world_object``.
        q_xyzw: orientation of the object frame (x forward, z up) in the world frame, a unit
            quaternion ``(x, y, z, w)`` (norm within ``wire.QUAT_NORM_TOL`` of 1, kept as given).
        yaw: heading of the object's x axis about world z, radians.
        size: extent along the object's x, y, z, metres (>= 0).
        bounds_min, bounds_max: world-axis-aligned bounds of the oriented box, metres.
        color_rgb: mean colour ``(R, G, B)`` in 0..255, or None when unknown.
        n_observations: stored observations (>= 0).
        first_seen_s, last_seen_s: server wall-clock seconds.
        robots: robots that observed it.
        confirmed: False while association has not confirmed the object.
        distance_m: distance of ``position`` from the query's ``near`` (>= 0), or None.
    """

    object_id: int
    category: str
    confidence: float
    position: Vec3
    q_xyzw: Vec4
    yaw: float
    size: Vec3
    bounds_min: Vec3
    bounds_max: Vec3
    color_rgb: Vec3 | None
    n_observations: int
    first_seen_s: float
    last_seen_s: float
    robots: tuple[str, ...]
    confirmed: bool = True
    distance_m: float | None = None

    def __post_init__(self) -> None:
        for name, check in _OBJECT_CHECKS:
            value = getattr(self, name)
            clean = check(value, name)
            if clean is not value:  # a list given as a tuple, an int as a float ...
                object.__setattr__(self, name, clean)

    @classmethod
    def checked_elsewhere(cls, **fields: Any) -> MapObject:
        """A message from values already checked where they were stored (the server's object
        map), without running the field checks again: they cost about 10 us an object, a
        millisecond on a page of 100. Every field must be given, of the documented types."""
        obj = object.__new__(cls)
        for f in _FIELD_NAMES:
            object.__setattr__(obj, f, fields[f])
        if len(fields) != len(_FIELD_NAMES):
            raise TypeError(f"unknown MapObject fields: {sorted(set(fields) - set(_FIELD_NAMES))}")
        return obj

    @property
    def T_world_object(self) -> NDArray[np.float64]:
        """The object's pose as a 4x4 transform (object frame -> world frame)."""
        return make_transform(quat_to_rotation(np.array(self.q_xyzw)), self.position)


_OBJECT_CHECKS: Final[tuple[tuple[str, Callable[[Any, str], Any]], ...]] = (
    ("object_id", lambda v, f: _int(v, f, 1)),
    ("category", lambda v, f: _name(v, f, 64)),
    ("confidence", lambda v, f: _float(v, f, 0.0, 1.0)),
    ("position", lambda v, f: _vec(v, f, 3)),
    ("q_xyzw", lambda v, f: _check_quat(_vec(v, f, 4), f)),
    ("yaw", _float),
    ("size", lambda v, f: _vec(v, f, 3, 0.0)),
    ("bounds_min", lambda v, f: _vec(v, f, 3)),
    ("bounds_max", lambda v, f: _vec(v, f, 3)),
    ("color_rgb", lambda v, f: None if v is None else _vec(v, f, 3)),
    ("n_observations", lambda v, f: _int(v, f, 0)),
    ("first_seen_s", _float),
    ("last_seen_s", _float),
    ("robots", _robots),
    ("confirmed", _bool),
    ("distance_m", lambda v, f: None if v is None else _float(v, f, 0.0)),
)
"""Each field of :class:`MapObject` with its check, which returns the value (converted where needed)."""
_FIELD_NAMES: Final = tuple(name for name, _ in _OBJECT_CHECKS)


@dataclass(frozen=True)
class ObjectsReply:
    """The queryable's answer (schema ``wardmap.map.objects``): one page of objects.

    Attributes:
        objects: the page, in the query's order (nearest first with ``near``, else by id).
        next_offset: the ``offset`` of the next page, or None on the last page.
    """

    objects: tuple[MapObject, ...]
    next_offset: int | None

    def __post_init__(self) -> None:
        if not isinstance(self.objects, list | tuple):
            raise WireError("objects", f"expected a list of objects, got {type(self.objects).__name__}")
        for i, obj in enumerate(self.objects):
            if not isinstance(obj, MapObject):
                raise WireError(f"objects[{i}]", f"expected a MapObject, got {type(obj).__name__}")
        object.__setattr__(self, "objects", tuple(self.objects))
        if self.next_offset is not None:
            object.__setattr__(self, "next_offset", _int(self.next_offset, "next_offset", 0))


@dataclass(frozen=True)
class MapUpdate:
    """One committed change of the map (schema ``wardmap.map.update``).

    Attributes:
        kind: ``created``, ``updated`` or ``deleted``.
        object: the object after the change (before it, for ``deleted``).
        merged_into: for a ``deleted`` object merged into another: that object's id.
    """

    kind: ChangeKind
    object: MapObject
    merged_into: int | None = None

    def __post_init__(self) -> None:
        if self.kind not in CHANGE_KINDS:
            raise WireError("kind", f"unknown kind {self.kind!r:.40}; expected one of {CHANGE_KINDS}")
        if not isinstance(self.object, MapObject):
            raise WireError("object", f"expected a MapObject, got {type(self.object).__name__}")
        if self.merged_into is not None:
            object.__setattr__(self, "merged_into", _int(self.merged_into, "merged_into", 1))
            if self.kind != "deleted":
                raise WireError("merged_into", f"only a deleted object is merged, not a {self.kind} one")


@dataclass(frozen=True)
class MapError:
    """A query the map server could not answer (schema ``wardmap.map.error``).

    Attributes:
        detail: what was wrong (e.g. the bad parameter), 1-:data:`MAX_DETAIL_LEN` characters.
    """

    detail: str

    def __post_init__(self) -> None:
        _name(self.detail, "detail", MAX_DETAIL_LEN)


MapMessage: TypeAlias = ObjectsReply | MapUpdate | MapError


# --------------------------------------------------------------------------- encode


def object_to_wire(obj: MapObject) -> dict[str, Any]:
    """The object map of ``obj``: the JSON of REST and the msgpack map of Zenoh (same fields;
    vectors are tuples, which both write as arrays)."""
    return {
        "object_id": obj.object_id, "category": obj.category, "confidence": obj.confidence,
        "position": obj.position, "q_xyzw": obj.q_xyzw,
        "T_world_object": {"t": obj.position, "q_xyzw": obj.q_xyzw},
        "yaw": obj.yaw, "size": obj.size, "bounds_min": obj.bounds_min, "bounds_max": obj.bounds_max,
        "color_rgb": obj.color_rgb, "n_observations": obj.n_observations, "first_seen_s": obj.first_seen_s,
        "last_seen_s": obj.last_seen_s, "robots": obj.robots, "confirmed": obj.confirmed,
        "distance_m": obj.distance_m,
    }


def _to_wire(msg: MapMessage) -> dict[str, Any]:
    if isinstance(msg, ObjectsReply):
        return {"schema": SCHEMA_OBJECTS, "version": VERSION,
                "objects": [object_to_wire(o) for o in msg.objects], "next_offset": msg.next_offset}
    if isinstance(msg, MapUpdate):
        return {"schema": SCHEMA_UPDATE, "version": VERSION, "kind": msg.kind,
                "object": object_to_wire(msg.object), "merged_into": msg.merged_into}
    if isinstance(msg, MapError):
        return {"schema": SCHEMA_ERROR, "version": VERSION, "detail": msg.detail}
    raise WireError("", f"cannot encode {type(msg).__name__}: not a map message")


def encode_map_message(msg: MapMessage) -> bytes:
    """msgpack bytes of a map message (``schema``, ``version`` 1 and its fields).

    Raises:
        WireError: ``msg`` is not a map message, or the payload exceeds :data:`MAX_MESSAGE_BYTES`.
    """
    payload: bytes = msgpack.packb(_to_wire(msg), use_bin_type=True)
    if len(payload) > MAX_MESSAGE_BYTES:
        raise WireError("", f"map message is {len(payload)} bytes, more than {MAX_MESSAGE_BYTES}")
    return payload


# --------------------------------------------------------------------------- decode


def object_from_wire(value: object, field: str = "object") -> MapObject:
    """Read and validate an object map (inverse of :func:`object_to_wire`).

    ``position`` and ``q_xyzw`` may be absent (servers before they were added send only
    ``T_world_object``); when present they must equal ``T_world_object``'s ``t`` and ``q_xyzw``.
    ``color_rgb`` and ``distance_m`` may be absent or nil.

    Raises:
        WireError: a missing, unknown, mistyped or out-of-range field, named under ``field``.
    """
    f = _Fields(value, field)
    pose = _Fields(f.get("T_world_object"), f.name("T_world_object"))
    t = _vec(pose.get("t"), pose.name("t"), 3)
    q = _vec(pose.get("q_xyzw"), pose.name("q_xyzw"), 4)
    pose.done()
    _check_quat(q, pose.name("q_xyzw"))
    for key, pose_key, want in (("position", "t", t), ("q_xyzw", "q_xyzw", q)):
        flat = f.optional(key)
        if flat is not None and _vec(flat, f.name(key), len(want)) != want:
            raise WireError(f.name(key), f"differs from {pose.name(pose_key)}")
    args = {key: f.get(key) for key in (
        "object_id", "category", "confidence", "yaw", "size", "bounds_min", "bounds_max",
        "n_observations", "first_seen_s", "last_seen_s", "robots", "confirmed")}
    args["color_rgb"] = f.optional("color_rgb")
    args["distance_m"] = f.optional("distance_m")
    f.done()
    try:
        return MapObject(position=t, q_xyzw=q, **args)  # type: ignore[arg-type]  # checked in __post_init__
    except WireError as exc:
        raise WireError(f.name(exc.field), str(exc).split(": ", 1)[-1]) from exc


def _objects_from_wire(f: _Fields) -> ObjectsReply:
    raw = f.get("objects")
    if not isinstance(raw, list):
        raise WireError("objects", f"expected a list, got {type(raw).__name__}")
    objects = tuple(object_from_wire(o, f"objects[{i}]") for i, o in enumerate(raw))
    next_offset = f.get("next_offset")
    f.done()
    return ObjectsReply(objects, next_offset)


def _update_from_wire(f: _Fields) -> MapUpdate:
    kind = f.get("kind")
    obj = object_from_wire(f.get("object"), "object")
    merged_into = f.optional("merged_into")
    f.done()
    return MapUpdate(kind, obj, merged_into)


def _error_from_wire(f: _Fields) -> MapError:
    detail = f.get("detail")
    f.done()
    return MapError(detail)


_READERS: Final[Mapping[str, Callable[[_Fields], MapMessage]]] = MappingProxyType({
    SCHEMA_OBJECTS: _objects_from_wire, SCHEMA_UPDATE: _update_from_wire, SCHEMA_ERROR: _error_from_wire,
})


def decode_map_message(payload: bytes, *, max_bytes: int = MAX_MESSAGE_BYTES) -> MapMessage:
    """Parse and validate a map message (objects reply, update or error) from untrusted bytes.

    Raises:
        WireError: oversize, not msgpack, not a map, unknown schema or version, or any bad
            field; ``.field`` is its dotted path (``objects[0].T_world_object.q_xyzw``),
            ``""`` for the payload as a whole.
    """
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise WireError("", f"expected bytes, got {type(payload).__name__}")
    if len(payload) > max_bytes:
        raise WireError("", f"map message of {len(payload)} bytes exceeds {max_bytes}")
    try:
        message = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=True, max_ext_len=0)
    except (ValueError, TypeError, OverflowError, RecursionError, msgpack.UnpackException) as exc:
        raise WireError("", f"not a msgpack map message: {exc}"[:300]) from exc
    f = _Fields(message, "")
    schema = f.get("schema")
    if schema not in SCHEMAS:
        raise WireError("schema", f"unknown map schema {str(schema)[:60]!r}")
    version = f.get("version")
    if isinstance(version, bool) or version != VERSION:
        raise WireError("version", f"unsupported version {version!r:.20} of {schema}")
    return _READERS[schema](f)
