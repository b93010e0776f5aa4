"""Tests for the hospital knowledge graph (paper 001 Sec. 3.2), wardmap.shared.knowledge."""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from wardmap.shared.errors import KnowledgeGraphError, WardmapError
from wardmap.shared.knowledge import (
    BACKGROUND,
    EntityClass,
    KnowledgeGraph,
    Mobility,
    Relation,
)

CANONICAL = (
    ("person", Mobility.MOVING),
    ("wheelchair", Mobility.MOVABLE),
    ("cart", Mobility.MOVABLE),
    ("iv_pole", Mobility.MOVABLE),
    ("temperature_gun", Mobility.MOVABLE),
    ("cup", Mobility.MOVABLE),
    ("chair", Mobility.MOVABLE),
    ("bed", Mobility.STATIC),
    ("door", Mobility.STATIC),
    ("cabinet", Mobility.STATIC),
    ("wall_monitor", Mobility.STATIC),
    ("sink", Mobility.STATIC),
    ("desk", Mobility.STATIC),
)

VALID = """\
version = 1

[predicates]
pushes = "subject pushes object"
sits_on = "subject sits on object"

[[classes]]
name = "person"
mobility = "moving"
description = "a human"
roles = ["staff", "patient"]
color_rgb = [255, 0, 0]

[[classes]]
name = "wheelchair"
mobility = "movable"
description = "a wheelchair"
color_rgb = [0, 255, 0]

[[classes]]
name = "door"
mobility = "static"
description = "a door"
color_rgb = [0, 0, 255]

[[relations]]
subject = "person"
predicate = "pushes"
object = "wheelchair"

[[relations]]
subject = "person"
predicate = "sits_on"
object = "wheelchair"
"""


@pytest.fixture(scope="module")
def kg() -> KnowledgeGraph:
    """The packaged knowledge graph, loaded once per module."""
    return KnowledgeGraph.load()


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "kg.toml"
    path.write_text(text, encoding="utf-8")
    return path


# ---------------------------------------------------------------------- packaged file


def test_packaged_file_loads_with_canonical_classes_in_order(kg: KnowledgeGraph) -> None:
    """The packaged file loads and lists the 13 canonical classes in segmentation order."""
    assert kg.names == tuple(name for name, _ in CANONICAL)
    assert kg.num_classes == len(CANONICAL) + 1
    assert [entity.index for entity in kg.classes] == list(range(1, len(CANONICAL) + 1))
    assert kg.version == 1


def test_load_by_path_equals_packaged_load(kg: KnowledgeGraph) -> None:
    """Loading the source-tree file by explicit path gives the same classes and relations."""
    import wardmap.shared.data as data_pkg

    path = Path(data_pkg.__file__).parent / "knowledge_graph.toml"
    other = KnowledgeGraph.load(path)
    assert other.classes == kg.classes
    assert other.relations() == kg.relations()
    assert KnowledgeGraph.load(str(path)).names == kg.names


def test_every_class_has_expected_mobility(kg: KnowledgeGraph) -> None:
    """Each canonical class carries the mobility the paper assigns it (Sec. 3.2)."""
    for name, mobility in CANONICAL:
        assert kg.mobility(name) is mobility
        assert isinstance(kg.entity(name).mobility, Mobility)


def test_person_moving_wheelchair_movable_door_static(kg: KnowledgeGraph) -> None:
    """People are P_moving, wheelchairs P_movable, doors static; predicates agree."""
    assert kg.is_moving("person")
    assert not kg.is_movable("person") and not kg.is_static("person")
    assert kg.is_movable("wheelchair")
    assert not kg.is_moving("wheelchair") and not kg.is_static("wheelchair")
    assert kg.is_static("door")
    assert not kg.is_moving("door") and not kg.is_movable("door")
    assert kg.moving_classes() == ("person",)
    assert kg.movable_classes() == (
        "wheelchair",
        "cart",
        "iv_pole",
        "temperature_gun",
        "cup",
        "chair",
    )
    assert set(kg.static_classes()) == {"bed", "door", "cabinet", "wall_monitor", "sink", "desk"}


def test_person_roles_are_subtypes_not_classes(kg: KnowledgeGraph) -> None:
    """Staff, patient and visitor are roles of person, not separate segmentation classes."""
    assert kg.entity("person").roles == ("staff", "patient", "visitor")
    for role in ("staff", "patient", "visitor"):
        assert role not in kg.names
    assert all(entity.roles == () for entity in kg.classes if entity.name != "person")


def test_descriptions_and_colours_are_present_and_distinct(kg: KnowledgeGraph) -> None:
    """Every class has a description and a unique non-black display colour."""
    colours = [entity.color_rgb for entity in kg.classes]
    assert len(set(colours)) == len(colours)
    assert (0, 0, 0) not in colours
    assert all(entity.description.strip() for entity in kg.classes)
    lut = kg.color_lut()
    assert lut.shape == (kg.num_classes, 3) and lut.dtype == np.uint8
    assert tuple(lut[0]) == (0, 0, 0)
    assert tuple(lut[kg.index_of("person")]) == kg.entity("person").color_rgb


def test_index_name_round_trip(kg: KnowledgeGraph) -> None:
    """index_of and name_of are inverse over every label, background (0) included."""
    assert kg.name_of(0) == BACKGROUND
    assert kg.index_of(BACKGROUND) == 0
    for index in range(kg.num_classes):
        assert kg.index_of(kg.name_of(index)) == index
    for name in kg.names:
        assert kg.name_of(kg.index_of(name)) == name
    assert kg.index_of("person") == 1
    assert kg.index_of("desk") == 13


def test_mobility_lut_matches_classes(kg: KnowledgeGraph) -> None:
    """The LUT maps each label to 0 static / 1 movable / 2 moving, background static."""
    lut = kg.mobility_lut()
    assert lut.dtype == np.uint8
    assert lut.shape == (kg.num_classes,)
    assert lut[0] == 0
    expected_codes = {Mobility.STATIC: 0, Mobility.MOVABLE: 1, Mobility.MOVING: 2}
    for entity in kg.classes:
        assert lut[entity.index] == expected_codes[entity.mobility] == entity.mobility.code


def test_mobility_lut_classifies_a_label_image(kg: KnowledgeGraph) -> None:
    """Indexing the LUT with a random label image gives each pixel its class's mobility."""
    rng = np.random.default_rng(7)
    labels = rng.integers(0, kg.num_classes, size=(24, 32), dtype=np.uint8)
    codes = kg.mobility_lut()[labels]
    assert codes.shape == labels.shape
    for index in range(kg.num_classes):
        expected = kg.mobility(kg.name_of(index)).code
        assert np.all(codes[labels == index] == expected)


def test_mobility_lut_is_a_fresh_copy(kg: KnowledgeGraph) -> None:
    """Mutating a returned LUT does not change the graph or later LUTs."""
    lut = kg.mobility_lut()
    lut[:] = 9
    assert kg.mobility_lut()[kg.index_of("person")] == 2


def test_required_relations_present(kg: KnowledgeGraph) -> None:
    """The packaged graph holds the Fig. 2 style facts the tracker and simulator rely on."""
    facts = {(r.subject, r.predicate, r.object) for r in kg.relations()}
    required = {
        ("person", "pushes", "wheelchair"),
        ("person", "pushes", "cart"),
        ("person", "pushes", "iv_pole"),
        ("person", "carries", "temperature_gun"),
        ("person", "carries", "cup"),
        ("person", "sits_on", "chair"),
        ("person", "sits_on", "wheelchair"),
        ("person", "sits_on", "bed"),
        ("person", "lies_on", "bed"),
        ("iv_pole", "stands_beside", "bed"),
        ("wheelchair", "stands_beside", "bed"),
        ("chair", "stands_beside", "bed"),
    }
    for thing in ("temperature_gun", "cup"):
        for surface in ("desk", "cabinet", "cart"):
            required.add((thing, "placed_on", surface))
    assert required <= facts
    assert set(kg.predicates) >= {r.predicate for r in kg.relations()}


def test_relations_filtering(kg: KnowledgeGraph) -> None:
    """Filters on subject, predicate and object combine with AND; None matches anything."""
    pushed = kg.relations(subject="person", predicate="pushes")
    assert {r.object for r in pushed} == {"wheelchair", "cart", "iv_pole"}
    assert all(isinstance(r, Relation) for r in pushed)
    on_bed = kg.relations(object="bed")
    assert {(r.subject, r.predicate) for r in on_bed} >= {
        ("person", "sits_on"),
        ("person", "lies_on"),
        ("iv_pole", "stands_beside"),
    }
    assert kg.relations(subject="person", predicate="lies_on", object="bed") == (
        Relation("person", "lies_on", "bed"),
    )
    assert kg.relations(subject="door") == ()
    assert len(kg.relations()) == len(set(kg.relations()))


def test_relations_filter_rejects_unknown_names(kg: KnowledgeGraph) -> None:
    """A typo in a filter raises instead of silently matching nothing."""
    with pytest.raises(KnowledgeGraphError, match="unknown class 'persn'"):
        kg.relations(subject="persn")
    with pytest.raises(KnowledgeGraphError, match="unknown class 'bedd'"):
        kg.relations(object="bedd")
    with pytest.raises(KnowledgeGraphError, match=r"unknown predicate 'push'.*pushes"):
        kg.relations(predicate="push")


def test_unknown_class_lookup_lists_known_classes(kg: KnowledgeGraph) -> None:
    """Looking up an unknown class raises a WardmapError that lists the known classes."""
    for lookup in (kg.index_of, kg.mobility, kg.is_moving, kg.is_static, kg.entity):
        with pytest.raises(KnowledgeGraphError) as info:
            lookup("ventilator")
        message = str(info.value)
        assert "'ventilator'" in message
        assert "person" in message and "desk" in message
        assert isinstance(info.value, WardmapError)


@pytest.mark.parametrize("index", [-1, 14, 100])
def test_name_of_out_of_range(kg: KnowledgeGraph, index: int) -> None:
    """name_of rejects labels outside 0..N with the valid range in the message."""
    with pytest.raises(KnowledgeGraphError, match=r"out of range 0\.\.13"):
        kg.name_of(index)


def test_entities_and_relations_are_frozen(kg: KnowledgeGraph) -> None:
    """EntityClass and Relation are immutable, and classes is a tuple."""
    person = kg.entity("person")
    assert isinstance(person, EntityClass)
    assert isinstance(kg.classes, tuple)
    # setattr: the direct assignment is a static type error; here it must fail at run time.
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(person, "mobility", Mobility.STATIC)  # noqa: B010
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(kg.relations()[0], "subject", "door")  # noqa: B010


# ---------------------------------------------------------------------- custom files


def test_small_valid_file_loads(tmp_path: Path) -> None:
    """A minimal hand-written file loads; optional roles default to empty."""
    kg = KnowledgeGraph.load(_write(tmp_path, VALID))
    assert kg.names == ("person", "wheelchair", "door")
    assert kg.entity("person").roles == ("staff", "patient")
    assert kg.entity("door").roles == ()
    assert kg.relations(predicate="sits_on") == (Relation("person", "sits_on", "wheelchair"),)
    assert list(kg.mobility_lut()) == [0, 2, 1, 0]


def test_from_mapping_accepts_parsed_toml() -> None:
    """from_mapping builds the same graph from already-parsed TOML without a file."""
    kg = KnowledgeGraph.from_mapping(tomllib.loads(VALID), source="inline")
    assert kg.names == ("person", "wheelchair", "door")


# (scenario id, edit applied to VALID, fragment the error message must contain)
MALFORMED: list[tuple[str, Callable[[str], str], str]] = [
    ("malformed_toml", lambda t: t.replace('name = "door"', "name = door"), "malformed TOML"),
    (
        "unknown_mobility",
        lambda t: t.replace('mobility = "static"', 'mobility = "rolling"'),
        "unknown mobility 'rolling'; expected one of moving, movable, static",
    ),
    (
        "duplicate_class",
        lambda t: t.replace('name = "door"', 'name = "person"'),
        "duplicate class 'person'",
    ),
    (
        "relation_unknown_object",
        lambda t: t.replace('object = "wheelchair"\n\n', 'object = "trolley"\n\n', 1),
        "unknown object class 'trolley'",
    ),
    (
        "relation_unknown_subject",
        lambda t: t.replace('subject = "person"', 'subject = "nurse"', 1),
        "unknown subject class 'nurse'",
    ),
    (
        "unknown_predicate",
        lambda t: t.replace('predicate = "pushes"', 'predicate = "drags"'),
        "unknown predicate 'drags'; allowed predicates: pushes, sits_on",
    ),
    (
        "missing_class_field",
        lambda t: t.replace('description = "a wheelchair"\n', ""),
        "classes[1] ('wheelchair'): missing field(s): description",
    ),
    (
        "missing_relation_field",
        lambda t: t.replace('predicate = "sits_on"\n', ""),
        "relations[1]: missing field(s): predicate",
    ),
    ("missing_version", lambda t: t.replace("version = 1\n", ""), "missing field(s): version"),
    (
        "missing_predicates",
        lambda t: t.replace(
            '[predicates]\npushes = "subject pushes object"\nsits_on = "subject sits on object"\n',
            "",
        ),
        "missing field(s): predicates",
    ),
    ("unsupported_version", lambda t: t.replace("version = 1", "version = 7"), "version 7"),
    (
        "unknown_class_field",
        lambda t: t.replace('description = "a door"', 'description = "a door"\nmobilty = "x"'),
        "unknown field(s): mobilty",
    ),
    (
        "bad_colour",
        lambda t: t.replace("[0, 0, 255]", "[0, 0, 256]"),
        "color_rgb must be three integers in 0..255",
    ),
    (
        "duplicate_colour",
        lambda t: t.replace("[0, 0, 255]", "[0, 255, 0]"),
        "already used by 'wheelchair'",
    ),
    (
        "background_name_reserved",
        lambda t: t.replace('name = "door"', 'name = "background"'),
        "reserved for label 0",
    ),
    (
        "non_snake_case_name",
        lambda t: t.replace('name = "door"', 'name = "Door"'),
        "'Door' is not a snake_case name",
    ),
    (
        "duplicate_relation",
        lambda t: t.replace('predicate = "sits_on"', 'predicate = "pushes"'),
        "duplicate relation (person, pushes, wheelchair)",
    ),
    (
        "classes_not_array_of_tables",
        lambda t: "version = 1\nclasses = 3\nrelations = []\n[predicates]\na = 'b'\n",
        "classes must be an array of tables",
    ),
]


@pytest.mark.parametrize(
    ("edit", "fragment"),
    [(edit, fragment) for _, edit, fragment in MALFORMED],
    ids=[scenario for scenario, _, _ in MALFORMED],
)
def test_malformed_file_raises_with_useful_message(
    tmp_path: Path, edit: Callable[[str], str], fragment: str
) -> None:
    """Each malformed variant of a valid file raises KnowledgeGraphError naming the problem
    and the file it came from (scenario given by the test id)."""
    text = edit(VALID)
    assert text != VALID, "the edit must change the file"
    path = _write(tmp_path, text)
    with pytest.raises(KnowledgeGraphError) as info:
        KnowledgeGraph.load(path)
    message = str(info.value)
    assert fragment in message
    assert str(path) in message


def test_missing_file_raises(tmp_path: Path) -> None:
    """A path that does not exist raises KnowledgeGraphError naming the path."""
    missing = tmp_path / "nope.toml"
    with pytest.raises(KnowledgeGraphError, match=r"not found.*nope\.toml"):
        KnowledgeGraph.load(missing)


def test_non_utf8_file_raises(tmp_path: Path) -> None:
    """A file that is not UTF-8 text raises KnowledgeGraphError, not UnicodeDecodeError."""
    path = tmp_path / "kg.toml"
    path.write_bytes(b"version = 1\n\xff\xfe\n")
    with pytest.raises(KnowledgeGraphError, match="not UTF-8"):
        KnowledgeGraph.load(path)


def test_constructor_rejects_wrong_index() -> None:
    """Building a graph directly with indices out of file order is rejected."""
    door = EntityClass("door", 2, Mobility.STATIC, "a door", (), (1, 2, 3))
    with pytest.raises(KnowledgeGraphError, match="index 2, expected 1"):
        KnowledgeGraph([door], [], {"pushes": "p"})
