"""The persistent object map: object landmarks, their observations and spatial queries.

Association (paper 000 Sec. III) turns object measurements into landmarks; this module
checks them and keeps them in the server's store (:class:`~wardmap.server.store.ObjectStore`)
and answers "which objects, where". The store keeps:

- objects: one per landmark: category, confidence, ``T_world_object``, its position, yaw,
  size, world-axis bounds, mean colour, and values derived from its observations (count,
  first/last seen, robots);
- observations: one per measurement of an object in a keyframe, keyed by
  ``(robot_id, session_id, seq, box)``, so sending the same measurement again moves or
  refreshes it instead of adding a copy.

A radius query takes the objects whose bounds meet the cube around the centre, then keeps
those whose centre lies within the exact (float64) distance.

Frames and units: ``world`` is the frame association works in (a robot session's odom
frame until multi-robot alignment gives ``T_map_odom``). The object frame has x forward and
z up, origin at the centre of its box (``server/perception/types.py``). Metres, radians;
``*_s`` values are the server's wall-clock seconds (``time.time()``), ``stamp`` is the
robot's capture time.

Threads: :class:`ObjectMap` is thread safe like the store. Writes are serialised by a lock so
that listeners receive :class:`ObjectChange` events in commit order; listeners run on the
writer's thread after the commit.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Final, Literal, Protocol, TypeAlias

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.server.store import (
    CompactPage,
    CompactRow,
    KeyframeRef,
    ObjectDetail,
    ObjectHit,
    ObjectPage,
    ObjectRecord,
    ObjectRow,
    ObjectStore,
    Observation,
    ObservationRecord,
    UnknownObjectError,
)
from wardmap.server.store.records import Vec3
from wardmap.shared.errors import ConfigError, GeometryError, WardmapError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.se3 import check_transform, rotation_to_quat
from wardmap.shared.zenoh_config import validate_robot_id

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_LIMIT",
    "MAX_LIMIT",
    "CompactPage",
    "CompactRow",
    "KeyframeRef",
    "ObjectChange",
    "ObjectDetail",
    "ObjectHit",
    "ObjectMap",
    "ObjectMapError",
    "ObjectPage",
    "ObjectQuery",
    "ObjectRecord",
    "ObjectState",
    "Observation",
    "ObservationRecord",
    "from_landmark",
    "parse_near",
]

DEFAULT_LIMIT: Final = 100
MAX_LIMIT: Final = 1000
"""Largest page of :meth:`ObjectMap.find`."""
MAX_OFFSET: Final = 1_000_000
MAX_OBSERVATIONS: Final = 1000
MAX_COORD_M: Final = 1e6
"""Largest ``abs`` of a query's ``near`` coordinate in metres (1000 km: far beyond any site;
a distance from 1e155 m overflows float64, and its JSON would fail)."""
"""Most observations :meth:`ObjectMap.get` returns for one object."""

ChangeKind: TypeAlias = Literal["created", "updated", "deleted"]


class ObjectMapError(WardmapError):
    """A bad argument to the object map (bad object, observation or query) or an unknown object."""


# --------------------------------------------------------------------------- records


@dataclass(frozen=True, eq=False)
class ObjectState:
    """What association knows about one landmark: the input of :meth:`ObjectMap.upsert`.

    Attributes:
        object_id: landmark id, an int in [1, 2**63).
        category: knowledge-graph class name.
        confidence: in [0, 1].
        T_world_object: (4, 4) float64 object pose in ``world`` (x forward, z up, origin at
            the box centre).
        size: (3,) float64 box extent along the object's x, y, z, metres (>= 0).
        color_rgb: mean colour, 0..255 per channel, or None when unknown.
        confirmed: False for a landmark association has not confirmed
            (``Landmark.confirmed``); queries leave it out unless asked.
    """

    object_id: int
    category: str
    confidence: float
    T_world_object: NDArray[np.float64]
    size: NDArray[np.float64]
    color_rgb: Vec3 | None = None
    confirmed: bool = True


@dataclass(frozen=True, eq=False)
class ObjectChange:
    """An event produced by a committed write.

    Attributes:
        kind: ``created``, ``updated`` or ``deleted``.
        record: the object after the change (before it, for ``deleted``).
        merged_into: for ``deleted``: the object that took over its observations, if any.
    """

    kind: ChangeKind
    record: ObjectRecord
    merged_into: int | None = None


# --------------------------------------------------------------------------- queries


def parse_near(text: str) -> Vec3:
    """``"x,y,z"`` (metres, world frame) as a float triple; ObjectMapError otherwise."""
    parts = text.split(",") if isinstance(text, str) else []
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) and abs(v) <= MAX_COORD_M for v in values):
        raise ObjectMapError(f"near must be three finite numbers 'x,y,z' in metres, got {str(text)[:80]!r} "
                             f"(each within +-{MAX_COORD_M:g})")
    return values[0], values[1], values[2]


@dataclass(frozen=True, slots=True)
class ObjectQuery:
    """Filters of :meth:`ObjectMap.find`; validated on construction (ObjectMapError).

    Attributes:
        category: only this class (checked against the knowledge graph by the map).
        near: world point (x, y, z) in metres: results are ordered nearest first by the
            distance of their centre, and carry that distance.
        radius_m: with ``near``: only objects whose centre is within this distance (>= 0).
        min_confidence: only objects with confidence >= this, in [0, 1].
        robot: only objects some observation of this robot supports.
        limit: page size, 1..:data:`MAX_LIMIT`.
        offset: results to skip, 0..:data:`MAX_OFFSET`.
        include_unconfirmed: also objects association has not confirmed
            (:attr:`ObjectState.confirmed`); by default only confirmed ones.
    """

    category: str | None = None
    near: Vec3 | None = None
    radius_m: float | None = None
    min_confidence: float | None = None
    robot: str | None = None
    limit: int = DEFAULT_LIMIT
    offset: int = 0
    include_unconfirmed: bool = False

    def __post_init__(self) -> None:
        if self.category is not None and (not isinstance(self.category, str) or not self.category):
            raise ObjectMapError(f"category must be a non-empty str, got {self.category!r:.80}")
        if self.near is not None and (
            len(self.near) != 3 or not all(_is_finite(v) and abs(v) <= MAX_COORD_M for v in self.near)
        ):
            raise ObjectMapError(f"near must be three finite numbers within +-{MAX_COORD_M:g} m, "
                                 f"got {self.near!r:.80}")
        if self.radius_m is not None:
            if self.near is None:
                raise ObjectMapError("radius needs near=x,y,z (the centre of the search)")
            if not _is_finite(self.radius_m) or self.radius_m < 0:
                raise ObjectMapError(f"radius must be a finite number >= 0 metres, got {self.radius_m!r:.80}")
        if self.min_confidence is not None and (
            not _is_finite(self.min_confidence) or not 0 <= self.min_confidence <= 1
        ):
            raise ObjectMapError(f"min_confidence must be in [0, 1], got {self.min_confidence!r:.80}")
        if self.robot is not None:
            try:
                validate_robot_id(self.robot)
            except ConfigError as exc:
                raise ObjectMapError(str(exc)) from exc
        if not _is_int(self.limit) or not 1 <= self.limit <= MAX_LIMIT:
            raise ObjectMapError(f"limit must be an int in [1, {MAX_LIMIT}], got {self.limit!r:.80}")
        if not _is_int(self.offset) or not 0 <= self.offset <= MAX_OFFSET:
            raise ObjectMapError(f"offset must be an int in [0, {MAX_OFFSET}], got {self.offset!r:.80}")
        if not isinstance(self.include_unconfirmed, bool):
            raise ObjectMapError(f"include_unconfirmed must be a bool, got {self.include_unconfirmed!r:.80}")

    @classmethod
    def from_params(cls, params: Iterable[tuple[str, str]]) -> ObjectQuery:
        """Parse text parameters (a URL query or a zenoh selector's parameters).

        Keys: ``category``, ``near`` (``x,y,z``), ``radius``, ``min_confidence``, ``robot``,
        ``limit``, ``offset``, ``include_unconfirmed`` (``true`` or ``false``); each at most
        once. Raises ObjectMapError naming the first bad, unknown or repeated key.
        """
        seen: dict[str, str] = {}
        for key, value in params:
            if key not in _PARAM_KEYS:
                raise ObjectMapError(f"unknown parameter {key[:40]!r}; expected {', '.join(_PARAM_KEYS)}")
            if key in seen:
                raise ObjectMapError(f"parameter {key!r} given twice")
            seen[key] = value
        near = parse_near(seen["near"]) if "near" in seen else None
        return cls(
            category=seen.get("category"),
            near=near,
            radius_m=_parse_float(seen, "radius"),
            min_confidence=_parse_float(seen, "min_confidence"),
            robot=seen.get("robot"),
            limit=_parse_int(seen, "limit", DEFAULT_LIMIT),
            offset=_parse_int(seen, "offset", 0),
            include_unconfirmed=_parse_bool(seen, "include_unconfirmed"),
        )


_PARAM_KEYS: Final = (
    "category", "near", "radius", "min_confidence", "robot", "limit", "offset", "include_unconfirmed",
)


def _parse_bool(params: Mapping[str, str], key: str) -> bool:
    value = params.get(key, "false")
    if value not in ("true", "false"):
        raise ObjectMapError(f"{key} must be true or false, got {value[:40]!r}")
    return value == "true"


def _parse_float(params: Mapping[str, str], key: str) -> float | None:
    if key not in params:
        return None
    try:
        value = float(params[key])
    except ValueError:
        raise ObjectMapError(f"{key} must be a number, got {params[key][:80]!r}") from None
    return value


def _parse_int(params: Mapping[str, str], key: str, default: int) -> int:
    if key not in params:
        return default
    try:
        return int(params[key])
    except ValueError:
        raise ObjectMapError(f"{key} must be an integer, got {params[key][:80]!r}") from None


# --------------------------------------------------------------------------- landmark adapter


class MeasurementLike(Protocol):
    """The attributes :func:`from_landmark` reads from a measurement (``ObjectMeasurement``)."""

    @property
    def keyframe(self) -> str: ...
    @property
    def stamp(self) -> float: ...
    @property
    def category(self) -> str: ...
    @property
    def confidence(self) -> float: ...
    @property
    def box_xyxy(self) -> NDArray[np.float64]: ...
    @property
    def T_world_object(self) -> NDArray[np.float64]: ...
    @property
    def size(self) -> NDArray[np.float64]: ...


def from_landmark(
    object_id: int,
    category: str,
    confidence: float,
    T_world_object: ArrayLike,
    size: ArrayLike,
    measurements: Iterable[MeasurementLike] = (),
    color_rgb: Vec3 | None = None,
    confirmed: bool = True,
) -> tuple[ObjectState, list[Observation]]:
    """Map an association landmark (plain fields) onto the map's input types.

    Each measurement's ``keyframe`` must be the server key ``"<robot>/<session>/<seq>"``
    (``server/perception/types.py``); offline keys (``"<dataset>/<stamp>"``) have no robot
    and raise ObjectMapError.

    Returns:
        ``(state, observations)`` for :meth:`ObjectMap.upsert`.
    """
    state = ObjectState(
        object_id, category, confidence, np.asarray(T_world_object, np.float64),
        np.asarray(size, np.float64), color_rgb, confirmed,
    )
    observations = []
    for m in measurements:
        parts = str(m.keyframe).split("/")
        if len(parts) != 3 or not parts[2].isdigit():
            raise ObjectMapError(f"measurement keyframe {m.keyframe!r:.80} is not '<robot>/<session>/<seq>'")
        observations.append(Observation(
            object_id, parts[0], parts[1], int(parts[2]), float(m.stamp), m.category, float(m.confidence),
            np.asarray(m.box_xyxy, np.float64), np.asarray(m.T_world_object, np.float64),
            np.asarray(m.size, np.float64),
        ))
    return state, observations


# --------------------------------------------------------------------------- the map


class ObjectMap:
    """The object map on the server's store; see the module docstring.

    Args:
        store: the open store; it must outlive this object (closing the store ends it).
        knowledge: classes allowed as categories (default: the packaged knowledge graph).
        clock: server wall-clock seconds (``time.time``).
    """

    def __init__(
        self,
        store: ObjectStore,
        *,
        knowledge: KnowledgeGraph | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self._store = store
        self._kg = knowledge if knowledge is not None else KnowledgeGraph.load()
        self._classes = frozenset(self._kg.names)
        self._clock = clock
        self._write_lock = threading.Lock()
        self._listeners: list[Callable[[ObjectChange], None]] = []

    @property
    def categories_known(self) -> tuple[str, ...]:
        """The knowledge-graph classes, in index order."""
        return self._kg.names

    @property
    def knowledge(self) -> KnowledgeGraph:
        """The knowledge graph whose classes are the allowed categories."""
        return self._kg

    # ------------------------------------------------------------------ listeners

    def add_listener(self, callback: Callable[[ObjectChange], None]) -> Callable[[], None]:
        """Call ``callback(change)`` for every change after its commit, in commit order, on
        the writer's thread (it should be quick). Returns a function that removes it."""
        with self._write_lock:
            self._listeners.append(callback)

        def remove() -> None:
            with self._write_lock:
                if callback in self._listeners:
                    self._listeners.remove(callback)

        return remove

    def _notify(self, changes: list[ObjectChange]) -> None:
        for callback in list(self._listeners):
            for change in changes:
                try:
                    callback(change)
                except Exception:
                    log.exception("object map listener %r failed on %s of object %d",
                                  callback, change.kind, change.record.object_id)

    # ------------------------------------------------------------------ writes

    def upsert(
        self, objects: Sequence[ObjectState], observations: Sequence[Observation] = ()
    ) -> list[ObjectChange]:
        """Create or replace ``objects`` and add (or move) ``observations``, in one transaction.

        An observation already stored under the same keyframe and box is moved to its new
        ``object_id`` and refreshed (association re-assigning a measurement). Derived values
        (count, first/last seen, robots) are recomputed for every object touched.

        Returns:
            One change per touched object: ``created`` for objects new in this call,
            ``updated`` for the others (also objects that lost an observation), objects of
            ``objects`` first in their order.

        Raises:
            ObjectMapError: a bad object or observation (nothing is written), two objects
                with one id, or an observation of an object that is neither given nor stored.
            StoreError: a database failure (nothing is written).
        """
        obj_rows = [self._object_row(o, i) for i, o in enumerate(objects)]
        obs_rows = [self._observation_row(o, i) for i, o in enumerate(observations)]
        ids = [r.object_id for r in obj_rows]
        if len(set(ids)) != len(ids):
            raise ObjectMapError("objects: the same object_id is given more than once")
        if not obj_rows and not obs_rows:
            return []
        with self._write_lock:
            now = self._now()
            try:
                written = self._store.write_objects(obj_rows, obs_rows, now)
            except UnknownObjectError as exc:
                raise ObjectMapError(str(exc)) from exc
            changes = [ObjectChange("created" if w.created else "updated", w.record) for w in written]
            self._notify(changes)
        return changes

    def add_observations(self, observations: Sequence[Observation]) -> list[ObjectChange]:
        """Add (or move) observations of stored objects; see :meth:`upsert`."""
        return self.upsert((), observations)

    def delete(self, object_id: int, *, merged_into: int | None = None) -> list[ObjectChange]:
        """Remove an object (association merged or discarded it), in one transaction.

        Args:
            object_id: the object to remove.
            merged_into: an object that takes over its observations (and so its robots);
                None: its observations are removed with it.

        Returns:
            ``[deleted]``, followed by ``updated`` of ``merged_into`` when given.

        Raises:
            ObjectMapError: an unknown ``object_id`` or ``merged_into``, or both equal.
        """
        oid = _check_id(object_id, "object_id")
        target = None if merged_into is None else _check_id(merged_into, "merged_into")
        if target == oid:
            raise ObjectMapError(f"object {oid} cannot be merged into itself")
        with self._write_lock:
            try:
                before, after = self._store.delete_object(oid, target)
            except UnknownObjectError as exc:
                raise ObjectMapError(str(exc)) from exc
            changes = [ObjectChange("deleted", before, target)]
            if after is not None:
                changes.append(ObjectChange("updated", after))
            self._notify(changes)
        return changes

    # ------------------------------------------------------------------ reads

    def query(
        self,
        category: str | None = None,
        near: Vec3 | None = None,
        radius: float | None = None,
        min_confidence: float | None = None,
        robot: str | None = None,
        limit: int = DEFAULT_LIMIT,
        offset: int = 0,
        include_unconfirmed: bool = False,
    ) -> ObjectPage:
        """Shorthand for ``find(ObjectQuery(...))``; ``radius`` in metres."""
        return self.find(ObjectQuery(category, near, radius, min_confidence, robot, limit, offset,
                                     include_unconfirmed))

    def find(self, q: ObjectQuery) -> ObjectPage:
        """Objects matching every filter of ``q``, ``q.limit`` per page from ``q.offset``.

        Order: nearest centre first when ``q.near`` is given (ties by id), else by id.
        With ``q.radius_m`` only objects whose centre is within that distance of ``near``.

        Raises:
            ObjectMapError: a category the knowledge graph does not know.
        """
        self._check_query_category(q)
        return self._store.find_objects(
            category=q.category, near=q.near, radius_m=q.radius_m, min_confidence=q.min_confidence,
            robot=q.robot, include_unconfirmed=q.include_unconfirmed, limit=q.limit, offset=q.offset,
        )

    def find_compact(self, q: ObjectQuery) -> CompactPage:
        """:meth:`find`'s page as compact rows ``(object_id, category, x, y, z, yaw, size_x,
        size_y, size_z)`` (metres, radians): what a map view draws, without the records.

        Raises:
            ObjectMapError: a category the knowledge graph does not know.
        """
        self._check_query_category(q)
        return self._store.find_compact(
            category=q.category, near=q.near, radius_m=q.radius_m, min_confidence=q.min_confidence,
            robot=q.robot, include_unconfirmed=q.include_unconfirmed, limit=q.limit, offset=q.offset,
        )

    def _check_query_category(self, q: ObjectQuery) -> None:
        if q.category is not None and q.category not in self._classes:
            raise ObjectMapError(
                f"unknown category {q.category[:40]!r}; known categories: {', '.join(self._kg.names)}"
            )

    def get(self, object_id: int, *, max_observations: int = 100) -> ObjectDetail | None:
        """One object with its latest ``max_observations`` observations (newest first) and the
        keyframes they came from; None when the object is unknown.

        Raises:
            ObjectMapError: a bad ``object_id`` or ``max_observations`` (0..:data:`MAX_OBSERVATIONS`).
        """
        oid = _check_id(object_id, "object_id")
        if not _is_int(max_observations) or not 0 <= max_observations <= MAX_OBSERVATIONS:
            raise ObjectMapError(
                f"max_observations must be an int in [0, {MAX_OBSERVATIONS}], got {max_observations!r:.80}"
            )
        return self._store.object_detail(oid, int(max_observations))

    def ids(self) -> list[int]:
        """Every object id, ascending (unconfirmed ones too)."""
        return self._store.object_ids()

    def categories(self, include_unconfirmed: bool = False) -> dict[str, int]:
        """Number of stored objects per knowledge-graph class (every class, in index order);
        confirmed ones only unless ``include_unconfirmed``."""
        counts = self._store.category_counts(include_unconfirmed=include_unconfirmed)
        out = {name: counts.pop(name, 0) for name in self._kg.names}
        out.update(sorted(counts.items()))  # classes of an older knowledge graph stay visible
        return out

    def count(self, *, unconfirmed: bool | None = None) -> int:
        """Number of stored objects; with ``unconfirmed`` True or False, of those (not) confirmed."""
        return self._store.count_objects(unconfirmed=unconfirmed)

    # ------------------------------------------------------------------ internals

    def _now(self) -> float:
        now = float(self._clock())
        if not math.isfinite(now) or now <= 0:
            raise ObjectMapError(f"clock returned {now}: expected positive seconds")
        return now

    def _object_row(self, obj: ObjectState, i: int) -> ObjectRow:
        where = f"objects[{i}]"
        if not isinstance(obj, ObjectState):
            raise ObjectMapError(f"{where}: expected an ObjectState, got {type(obj).__name__}")
        oid = _check_id(obj.object_id, f"{where}.object_id")
        self._check_category(obj.category, where)
        T = _check_pose(obj.T_world_object, f"{where}.T_world_object")
        size = _check_size(obj.size, f"{where}.size")
        confidence = _check_unit(obj.confidence, f"{where}.confidence")
        confirmed = _check_bool(obj.confirmed, f"{where}.confirmed")
        lo, hi = _bounds(T, size)
        q = rotation_to_quat(T[:3, :3])
        color = None
        if obj.color_rgb is not None:
            rgb = np.asarray(obj.color_rgb, dtype=np.float64)
            if rgb.shape != (3,) or not np.all(np.isfinite(rgb)) or rgb.min() < 0 or rgb.max() > 255:
                raise ObjectMapError(
                    f"{where}.color_rgb: expected 3 values in [0, 255], got {obj.color_rgb!r:.80}"
                )
            color = (float(rgb[0]), float(rgb[1]), float(rgb[2]))
        return ObjectRow(
            object_id=oid, category=obj.category, confidence=confidence, T_world_object=T,
            yaw=math.atan2(T[1, 0], T[0, 0]), q_xyzw=(float(q[0]), float(q[1]), float(q[2]), float(q[3])),
            size=(float(size[0]), float(size[1]), float(size[2])),
            bounds_min=(float(lo[0]), float(lo[1]), float(lo[2])),
            bounds_max=(float(hi[0]), float(hi[1]), float(hi[2])),
            color_rgb=color, confirmed=bool(confirmed),
        )

    def _observation_row(self, obs: Observation, i: int) -> Observation:
        where = f"observations[{i}]"
        if not isinstance(obs, Observation):
            raise ObjectMapError(f"{where}: expected an Observation, got {type(obs).__name__}")
        for name in ("robot_id", "session_id"):
            try:
                validate_robot_id(getattr(obs, name))  # session ids share the robot id alphabet
            except ConfigError as exc:
                raise ObjectMapError(f"{where}.{name}: {exc}") from exc
        if not _is_int(obs.seq) or not 0 <= obs.seq < 2**63:
            raise ObjectMapError(f"{where}.seq: expected an int in [0, 2**63), got {obs.seq!r:.80}")
        if not _is_finite(obs.stamp) or obs.stamp <= 0:
            raise ObjectMapError(f"{where}.stamp: expected positive seconds, got {obs.stamp!r:.80}")
        self._check_category(obs.category, where)
        box = np.asarray(obs.box_xyxy, dtype=np.float64)
        if box.shape != (4,) or not np.all(np.isfinite(box)) or box[2] < box[0] or box[3] < box[1]:
            raise ObjectMapError(f"{where}.box_xyxy: expected finite x1, y1, x2 >= x1, y2 >= y1, got {box}")
        T = _check_pose(obs.T_world_object, f"{where}.T_world_object")
        size = _check_size(obs.size, f"{where}.size")
        return Observation(
            object_id=_check_id(obs.object_id, f"{where}.object_id"),
            robot_id=obs.robot_id, session_id=obs.session_id, seq=int(obs.seq), stamp=float(obs.stamp),
            category=obs.category, confidence=_check_unit(obs.confidence, f"{where}.confidence"),
            box_xyxy=box, T_world_object=T, size=size,
        )

    def _check_category(self, category: object, where: str) -> None:
        if not isinstance(category, str) or category not in self._classes:
            raise ObjectMapError(
                f"{where}.category: unknown category {category!r:.40}; known: {', '.join(self._kg.names)}"
            )


# --------------------------------------------------------------------------- helpers


def _is_int(value: object) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def _is_finite(value: object) -> bool:
    return (
        isinstance(value, int | float | np.integer | np.floating)
        and not isinstance(value, bool)
        and math.isfinite(float(value))
    )


def _check_id(value: object, where: str) -> int:
    if not _is_int(value) or not 1 <= int(value) < 2**63:  # type: ignore[call-overload]  # checked int
        raise ObjectMapError(f"{where}: expected an int in [1, 2**63), got {value!r:.80}")
    return int(value)  # type: ignore[call-overload]  # checked int above


def _check_bool(value: object, where: str) -> int:
    if not isinstance(value, bool | np.bool_):
        raise ObjectMapError(f"{where}: expected a bool, got {value!r:.80}")
    return int(value)


def _check_unit(value: object, where: str) -> float:
    if not _is_finite(value) or not 0 <= float(value) <= 1:  # type: ignore[arg-type]  # checked number
        raise ObjectMapError(f"{where}: expected a number in [0, 1], got {value!r:.80}")
    return float(value)  # type: ignore[arg-type]  # checked number above


def _check_pose(T: object, where: str) -> NDArray[np.float64]:
    try:
        return check_transform(T, where)  # type: ignore[arg-type]  # any array-like; checked inside
    except (GeometryError, TypeError, ValueError) as exc:
        raise ObjectMapError(str(exc) if isinstance(exc, GeometryError) else f"{where}: {exc}") from exc


def _check_size(size: object, where: str) -> NDArray[np.float64]:
    try:
        s = np.asarray(size, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ObjectMapError(f"{where}: expected 3 numbers, got {size!r:.80}") from exc
    if s.shape != (3,) or not np.all(np.isfinite(s)) or np.any(s < 0):
        raise ObjectMapError(f"{where}: expected 3 finite extents >= 0 metres, got {size!r:.80}")
    return s


def _bounds(
    T: NDArray[np.float64], size: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """World-axis bounds of the box of extent ``size`` (3,) centred at the origin of ``T_world_object``."""
    half = np.abs(T[:3, :3]) @ (0.5 * size)
    return T[:3, 3] - half, T[:3, 3] + half
