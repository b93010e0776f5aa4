"""The hospital knowledge graph of paper 001 Sec. 3.2, loaded from a data file.

The paper defines a knowledge graph ``G = {E, R, F}``: entities ``E``, relations ``R``
and facts ``F``, each fact a triple ``(h, r, t)`` with ``h, t`` in ``E`` and ``r`` in
``R``. Every entity carries a mobility attribute: ``moving`` (people: staff, patients,
visitors; the paper's ``P_moving``), ``movable`` (things people push or carry, such as
wheelchairs and temperature guns; ``P_movable``) or ``static`` (beds, doors, stationary
equipment). Sec. 3.4 treats ``moving`` points as dynamic and ``movable`` points as
dynamic only when a moving entity is close to them.

The graph is data, not code: ``shared/data/knowledge_graph.toml`` (packaged as
``wardmap.shared.data``) holds the classes, their order (which is the segmentation
class index, 0 being the background), the allowed predicates and the facts.
:meth:`KnowledgeGraph.load` reads and validates it; every problem raises
:class:`~wardmap.shared.errors.KnowledgeGraphError` naming the offending entry.

Example::

    kg = KnowledgeGraph.load()
    kg.index_of("wheelchair")           # 2
    kg.is_movable("wheelchair")         # True
    lut = kg.mobility_lut()             # uint8, lut[label_image] -> mobility codes
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from wardmap.shared.errors import KnowledgeGraphError

__all__ = [
    "BACKGROUND",
    "BACKGROUND_INDEX",
    "SUPPORTED_VERSIONS",
    "EntityClass",
    "KnowledgeGraph",
    "Mobility",
    "Relation",
]

BACKGROUND = "background"
"""Name of label 0: pixels that belong to no entity class (static in the mobility LUT)."""

BACKGROUND_INDEX = 0
"""Segmentation label of the background."""

SUPPORTED_VERSIONS = (1,)
"""Values of the file's ``version`` field this module understands."""

PACKAGED_FILE = "knowledge_graph.toml"
"""File name of the packaged knowledge graph inside ``wardmap.shared.data``."""

_NAME_RE = re.compile(r"^[a-z][a-z0-9_]*$")
_TOP_KEYS = frozenset({"version", "predicates", "classes", "relations"})
_CLASS_REQUIRED = ("name", "mobility", "description", "color_rgb")
_CLASS_KEYS = frozenset({*_CLASS_REQUIRED, "roles"})
_RELATION_KEYS = ("subject", "predicate", "object")


class Mobility(StrEnum):
    """Mobility attribute of an entity class (paper 001 Sec. 3.2).

    ``MOVING`` entities have motion attributes of their own (``P_moving``: people);
    ``MOVABLE`` ones move only when a moving entity pushes or carries them
    (``P_movable``); ``STATIC`` ones are part of the building's fixed structure.
    """

    MOVING = "moving"
    MOVABLE = "movable"
    STATIC = "static"

    @property
    def code(self) -> int:
        """Integer code used in :meth:`KnowledgeGraph.mobility_lut`: static 0, movable 1,
        moving 2 (ordered by how readily a point of this class is dynamic)."""
        return _MOBILITY_CODES[self]


_MOBILITY_CODES: dict[Mobility, int] = {
    Mobility.STATIC: 0,
    Mobility.MOVABLE: 1,
    Mobility.MOVING: 2,
}


@dataclass(frozen=True)
class EntityClass:
    """One entity class of the knowledge graph, an element of ``E`` (paper 001 Sec. 3.2).

    Attributes:
        name: canonical snake_case class name shared by simulator and segmentation.
        index: segmentation label, 1..N in file order (0 is :data:`BACKGROUND`).
        mobility: moving, movable or static.
        description: one line saying what the class covers.
        roles: entity sub-types that share this class (``person``: staff, patient,
            visitor); empty for most classes. Roles are not separate labels.
        color_rgb: display colour for label visualisation, 0..255 per channel.
    """

    name: str
    index: int
    mobility: Mobility
    description: str
    roles: tuple[str, ...]
    color_rgb: tuple[int, int, int]


@dataclass(frozen=True)
class Relation:
    """One fact ``(h, r, t)`` of the knowledge graph (paper 001 Sec. 3.2).

    Attributes:
        subject: class name of the head entity ``h`` (e.g. ``"person"``).
        predicate: the relation ``r`` (e.g. ``"pushes"``), one of the file's predicates.
        object: class name of the tail entity ``t`` (e.g. ``"wheelchair"``).
    """

    subject: str
    predicate: str
    object: str


class KnowledgeGraph:
    """Immutable hospital knowledge graph ``G = {E, R, F}`` (paper 001 Sec. 3.2).

    Build it with :meth:`load` (or :meth:`from_mapping` for already-parsed data). The
    constructor checks that class indices run 1..N in order, names are unique, and
    every fact names known classes and an allowed predicate.

    Label 0 is :data:`BACKGROUND`: :meth:`name_of` and :meth:`index_of` accept it, and it
    counts as static in :meth:`mobility`, but it is not one of :attr:`classes`.
    """

    __slots__ = ("_by_name", "_classes", "_predicates", "_relations", "_version")

    def __init__(
        self,
        classes: Sequence[EntityClass],
        relations: Sequence[Relation],
        predicates: Mapping[str, str],
        version: int = 1,
        source: str = "<knowledge graph>",
    ) -> None:
        """Check cross-references and freeze the graph.

        Args:
            classes: entity classes; ``classes[i].index`` must be ``i + 1``.
            relations: facts; subjects and objects must be class names, predicates
                keys of ``predicates``.
            predicates: allowed predicate name -> one-line meaning.
            version: the file's format version.
            source: where the data came from, used in error messages.

        Raises:
            KnowledgeGraphError: on a duplicate class, a wrong index, a repeated colour,
                an unknown predicate, a fact naming an unknown class or a repeated fact.
        """
        if not classes:
            raise KnowledgeGraphError(f"{source}: no classes defined")
        by_name: dict[str, EntityClass] = {}
        for position, entity in enumerate(classes, start=1):
            if entity.name == BACKGROUND:
                raise KnowledgeGraphError(
                    f"{source}: class name {BACKGROUND!r} is reserved for label 0"
                )
            if entity.name in by_name:
                raise KnowledgeGraphError(f"{source}: duplicate class {entity.name!r}")
            if entity.index != position:
                raise KnowledgeGraphError(
                    f"{source}: class {entity.name!r} has index {entity.index}, "
                    f"expected {position} (indices follow file order from 1)"
                )
            by_name[entity.name] = entity
        _check_colors(classes, source)
        seen: set[Relation] = set()
        for relation in relations:
            for role, name in (("subject", relation.subject), ("object", relation.object)):
                if name not in by_name:
                    raise KnowledgeGraphError(
                        f"{source}: relation {_fmt(relation)} names unknown {role} class "
                        f"{name!r}; known classes: {', '.join(by_name)}"
                    )
            if relation.predicate not in predicates:
                raise KnowledgeGraphError(
                    f"{source}: relation {_fmt(relation)} uses unknown predicate "
                    f"{relation.predicate!r}; allowed predicates: {', '.join(predicates)}"
                )
            if relation in seen:
                raise KnowledgeGraphError(f"{source}: duplicate relation {_fmt(relation)}")
            seen.add(relation)
        self._classes: tuple[EntityClass, ...] = tuple(classes)
        self._by_name: dict[str, EntityClass] = by_name
        self._relations: tuple[Relation, ...] = tuple(relations)
        self._predicates: dict[str, str] = dict(predicates)
        self._version = version

    # ------------------------------------------------------------------ loading

    @classmethod
    def load(cls, path: str | Path | None = None) -> KnowledgeGraph:
        """Read and validate a knowledge-graph TOML file.

        Args:
            path: the file to read; ``None`` reads the packaged
                ``wardmap.shared.data/knowledge_graph.toml``.

        Raises:
            KnowledgeGraphError: if the file is missing, unreadable, not UTF-8, not
                valid TOML, or fails any check of :meth:`from_mapping`.
        """
        if path is None:
            source = f"wardmap.shared.data/{PACKAGED_FILE}"
            try:
                raw = resources.files("wardmap.shared.data").joinpath(PACKAGED_FILE).read_bytes()
            except OSError as exc:
                raise KnowledgeGraphError(f"{source}: cannot read: {exc}") from exc
        else:
            file = Path(path)
            source = str(file)
            if not file.is_file():
                raise KnowledgeGraphError(f"knowledge-graph file not found: {file}")
            try:
                raw = file.read_bytes()
            except OSError as exc:
                raise KnowledgeGraphError(f"{source}: cannot read: {exc}") from exc
        try:
            data = tomllib.loads(raw.decode("utf-8"))
        except UnicodeDecodeError as exc:
            raise KnowledgeGraphError(f"{source}: not UTF-8 text: {exc}") from exc
        except tomllib.TOMLDecodeError as exc:
            raise KnowledgeGraphError(f"{source}: malformed TOML: {exc}") from exc
        return cls.from_mapping(data, source=source)

    @classmethod
    def from_mapping(
        cls, data: Mapping[str, Any], source: str = "<knowledge graph>"
    ) -> KnowledgeGraph:
        """Build a graph from parsed TOML, checking every field.

        Expected layout: ``version`` (int), ``[predicates]`` (name -> meaning),
        ``[[classes]]`` (name, mobility, description, color_rgb, optional roles) and
        ``[[relations]]`` (subject, predicate, object). Unknown keys are errors so a
        typo never passes silently.

        Raises:
            KnowledgeGraphError: naming the source and the offending entry.
        """
        _check_keys(data, required=tuple(sorted(_TOP_KEYS)), allowed=_TOP_KEYS, where=source)
        version = data["version"]
        if not _is_int(version) or version not in SUPPORTED_VERSIONS:
            raise KnowledgeGraphError(
                f"{source}: unsupported version {version!r}; supported: "
                f"{', '.join(map(str, SUPPORTED_VERSIONS))}"
            )
        predicates = _parse_predicates(data["predicates"], source)
        raw_classes = _table_list(data["classes"], "classes", source)
        classes = [
            _parse_class(entry, index, source) for index, entry in enumerate(raw_classes, start=1)
        ]
        raw_relations = _table_list(data["relations"], "relations", source)
        relations = [
            _parse_relation(entry, number, source)
            for number, entry in enumerate(raw_relations, start=1)
        ]
        return cls(classes, relations, predicates, version=version, source=source)

    # ------------------------------------------------------------------ queries

    @property
    def version(self) -> int:
        """Format version of the file the graph came from."""
        return self._version

    @property
    def classes(self) -> tuple[EntityClass, ...]:
        """Entity classes in index order (``classes[i].index == i + 1``)."""
        return self._classes

    @property
    def names(self) -> tuple[str, ...]:
        """Class names in index order, without the background."""
        return tuple(entity.name for entity in self._classes)

    @property
    def num_classes(self) -> int:
        """Number of segmentation labels, including the background (N + 1)."""
        return len(self._classes) + 1

    @property
    def predicates(self) -> tuple[str, ...]:
        """Allowed relation names ``R`` in file order."""
        return tuple(self._predicates)

    def entity(self, name: str) -> EntityClass:
        """The entity class called ``name``; raises :class:`KnowledgeGraphError` if unknown."""
        entity = self._by_name.get(name)
        if entity is None:
            raise KnowledgeGraphError(
                f"unknown class {name!r}; known classes: {', '.join(self._by_name)}"
            )
        return entity

    def index_of(self, name: str) -> int:
        """Segmentation label of class ``name`` (``"background"`` -> 0)."""
        if name == BACKGROUND:
            return BACKGROUND_INDEX
        return self.entity(name).index

    def name_of(self, index: int) -> str:
        """Class name of segmentation label ``index`` (0 -> ``"background"``)."""
        if not _is_int(index) or not 0 <= index < self.num_classes:
            raise KnowledgeGraphError(
                f"class index {index!r} out of range 0..{self.num_classes - 1}; "
                f"known classes: {BACKGROUND}, {', '.join(self._by_name)}"
            )
        if index == BACKGROUND_INDEX:
            return BACKGROUND
        return self._classes[index - 1].name

    def mobility(self, name: str) -> Mobility:
        """Mobility of class ``name``; the background is static."""
        if name == BACKGROUND:
            return Mobility.STATIC
        return self.entity(name).mobility

    def is_moving(self, name: str) -> bool:
        """True if ``name`` has motion attributes of its own (``P_moving``, e.g. person)."""
        return self.mobility(name) is Mobility.MOVING

    def is_movable(self, name: str) -> bool:
        """True if ``name`` is moved by moving entities (``P_movable``, e.g. wheelchair)."""
        return self.mobility(name) is Mobility.MOVABLE

    def is_static(self, name: str) -> bool:
        """True if ``name`` is fixed structure (e.g. door) or the background."""
        return self.mobility(name) is Mobility.STATIC

    def moving_classes(self) -> tuple[str, ...]:
        """Names of the moving classes (``P_moving``), in index order."""
        return self._with_mobility(Mobility.MOVING)

    def movable_classes(self) -> tuple[str, ...]:
        """Names of the movable classes (``P_movable``), in index order."""
        return self._with_mobility(Mobility.MOVABLE)

    def static_classes(self) -> tuple[str, ...]:
        """Names of the static classes, in index order (background excluded)."""
        return self._with_mobility(Mobility.STATIC)

    def relations(
        self,
        subject: str | None = None,
        predicate: str | None = None,
        object: str | None = None,
    ) -> tuple[Relation, ...]:
        """Facts matching every given field, in file order (``None`` matches anything).

        Example: ``kg.relations(subject="person", predicate="pushes")``.

        Raises:
            KnowledgeGraphError: if a given class or predicate is unknown, so a typo
                does not silently return nothing.
        """
        for name in (subject, object):
            if name is not None:
                self.entity(name)
        if predicate is not None and predicate not in self._predicates:
            raise KnowledgeGraphError(
                f"unknown predicate {predicate!r}; allowed predicates: "
                f"{', '.join(self._predicates)}"
            )
        return tuple(
            relation
            for relation in self._relations
            if (subject is None or relation.subject == subject)
            and (predicate is None or relation.predicate == predicate)
            and (object is None or relation.object == object)
        )

    def mobility_lut(self) -> npt.NDArray[np.uint8]:
        """Look-up table from segmentation label to mobility code.

        Returns:
            A new ``(num_classes,)`` uint8 array: ``lut[label]`` is 0 static, 1 movable,
            2 moving (:attr:`Mobility.code`); ``lut[0]`` (background) is 0. Index it with
            a label image to classify every pixel at once: ``lut[labels]``.
        """
        lut = np.zeros(self.num_classes, dtype=np.uint8)
        for entity in self._classes:
            lut[entity.index] = entity.mobility.code
        return lut

    def color_lut(self) -> npt.NDArray[np.uint8]:
        """Look-up table from segmentation label to display colour.

        Returns:
            A new ``(num_classes, 3)`` uint8 RGB array; row 0 (background) is black.
            ``color_lut()[labels]`` turns an ``(H, W)`` label image into ``(H, W, 3)`` RGB.
        """
        lut = np.zeros((self.num_classes, 3), dtype=np.uint8)
        for entity in self._classes:
            lut[entity.index] = entity.color_rgb
        return lut

    def _with_mobility(self, mobility: Mobility) -> tuple[str, ...]:
        return tuple(entity.name for entity in self._classes if entity.mobility is mobility)

    def __repr__(self) -> str:
        return (
            f"KnowledgeGraph(version={self._version}, classes={len(self._classes)}, "
            f"relations={len(self._relations)})"
        )


# ---------------------------------------------------------------------- parsing helpers


def _is_int(value: object) -> bool:
    """True for a real integer (TOML booleans are Python ints and are rejected)."""
    return isinstance(value, int) and not isinstance(value, bool)


def _fmt(relation: Relation) -> str:
    return f"({relation.subject}, {relation.predicate}, {relation.object})"


def _check_keys(
    table: Mapping[str, Any], required: Sequence[str], allowed: frozenset[str], where: str
) -> None:
    missing = [key for key in required if key not in table]
    if missing:
        raise KnowledgeGraphError(f"{where}: missing field(s): {', '.join(missing)}")
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise KnowledgeGraphError(
            f"{where}: unknown field(s): {', '.join(unknown)}; allowed: "
            f"{', '.join(sorted(allowed))}"
        )


def _table_list(value: object, key: str, source: str) -> list[Mapping[str, Any]]:
    if not isinstance(value, list) or not all(isinstance(item, Mapping) for item in value):
        raise KnowledgeGraphError(f"{source}: {key} must be an array of tables ([[{key}]])")
    return value


def _text(table: Mapping[str, Any], key: str, where: str) -> str:
    value = table[key]
    if not isinstance(value, str) or not value.strip():
        raise KnowledgeGraphError(f"{where}: {key} must be a non-empty string, got {value!r}")
    return value


def _identifier(table: Mapping[str, Any], key: str, where: str) -> str:
    value = _text(table, key, where)
    if not _NAME_RE.match(value):
        raise KnowledgeGraphError(f"{where}: {key} {value!r} is not a snake_case name")
    return value


def _parse_predicates(value: object, source: str) -> dict[str, str]:
    if not isinstance(value, Mapping) or not value:
        raise KnowledgeGraphError(
            f"{source}: [predicates] must be a non-empty table of name = description"
        )
    predicates: dict[str, str] = {}
    for name, meaning in value.items():
        where = f"{source}: predicates.{name}"
        if not _NAME_RE.match(name):
            raise KnowledgeGraphError(f"{where}: predicate {name!r} is not a snake_case name")
        if not isinstance(meaning, str) or not meaning.strip():
            raise KnowledgeGraphError(f"{where}: description must be a non-empty string")
        predicates[name] = meaning
    return predicates


def _parse_class(entry: Mapping[str, Any], index: int, source: str) -> EntityClass:
    label = entry.get("name")
    where = f"{source}: classes[{index - 1}]" + (f" ({label!r})" if isinstance(label, str) else "")
    _check_keys(entry, required=_CLASS_REQUIRED, allowed=_CLASS_KEYS, where=where)
    name = _identifier(entry, "name", where)
    mobility_text = entry["mobility"]
    try:
        mobility = Mobility(mobility_text)
    except ValueError:
        raise KnowledgeGraphError(
            f"{where}: unknown mobility {mobility_text!r}; expected one of "
            f"{', '.join(m.value for m in Mobility)}"
        ) from None
    description = _text(entry, "description", where)
    roles = _parse_roles(entry.get("roles", []), where)
    color = entry["color_rgb"]
    if (
        not isinstance(color, list)
        or len(color) != 3
        or not all(_is_int(c) and 0 <= c <= 255 for c in color)
    ):
        raise KnowledgeGraphError(
            f"{where}: color_rgb must be three integers in 0..255, got {color!r}"
        )
    return EntityClass(
        name=name,
        index=index,
        mobility=mobility,
        description=description,
        roles=roles,
        color_rgb=(color[0], color[1], color[2]),
    )


def _parse_roles(value: object, where: str) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(
        isinstance(role, str) and _NAME_RE.match(role) for role in value
    ):
        raise KnowledgeGraphError(
            f"{where}: roles must be a list of snake_case names, got {value!r}"
        )
    if len(set(value)) != len(value):
        raise KnowledgeGraphError(f"{where}: duplicate role in {value!r}")
    return tuple(value)


def _check_colors(classes: Sequence[EntityClass], source: str) -> None:
    owner: dict[tuple[int, int, int], str] = {(0, 0, 0): BACKGROUND}
    for entity in classes:
        other = owner.get(entity.color_rgb)
        if other is not None:
            raise KnowledgeGraphError(
                f"{source}: class {entity.name!r} has color_rgb {list(entity.color_rgb)}, "
                f"already used by {other!r}; colours must be distinct (black is background)"
            )
        owner[entity.color_rgb] = entity.name


def _parse_relation(entry: Mapping[str, Any], number: int, source: str) -> Relation:
    where = f"{source}: relations[{number - 1}]"
    _check_keys(entry, required=_RELATION_KEYS, allowed=frozenset(_RELATION_KEYS), where=where)
    return Relation(
        subject=_identifier(entry, "subject", where),
        predicate=_identifier(entry, "predicate", where),
        object=_identifier(entry, "object", where),
    )
