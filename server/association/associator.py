"""The associator: object measurements of arriving keyframes -> object landmarks.

Methods (``AssociationConfig.method``):

- ``hierarchical`` (paper 000): keyframes form groups of M with j shared by neighbours
  (Sec. III-A, Fig. 3); inside a group the measurements are tracked into group
  landmarks (:mod:`.mot`); when a group is complete its landmarks are associated to the
  global landmarks by HDP Gibbs sampling with the Eq. 2-3 GMM likelihood (:mod:`.hdp`);
  each changed landmark's pose is refined by Eq. 4-6 (:mod:`.refine`); the group's
  measurements of classes seen whole move to the landmark with the nearest refined centre
  (``nearest_centre``, ours); a changed landmark
  whose box mostly lies inside (or holds) another of its class is merged with it
  (``merge_inside``, ours), and one half inside a landmark of another class, unless the
  knowledge graph says the two classes are found together (``merge_across``, ours).
- ``per_keyframe_hdp`` (HDP-SLAM): every keyframe is a group of single measurements; the
  landmark pose is its first measurement's.
- ``nearest``: greedy nearest neighbour by class and distance.

The live server calls :meth:`Associator.add_keyframe` as keyframes arrive, naming the
robot session they come from (``stream``): keyframe groups are formed per stream, so
interleaved robots never share a group, while all streams share the landmarks. It calls
:meth:`Associator.flush` at the end of a session; with ``hierarchical`` the landmarks
change when a group completes (every M - j keyframes of that stream). The associator owns all
of its state; callers get frozen :class:`Landmark` snapshots. Callers filter classes
that do not belong in the map (``moving`` ones such as people) before adding.

Every measurement given ends in exactly one landmark. A measurement of a keyframe shared
by two groups stays in the landmark the earlier group put it in. A merged landmark is
reported once as ``merged`` (with the id that took its measurements) and is gone after.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.server.association.baselines import NearestConfig, nearest_assign, per_keyframe_items
from wardmap.server.association.geometry import (
    cut_at_side,
    cut_at_top_or_bottom,
    is_truncated,
    project_box,
    world_extents,
)
from wardmap.server.association.groups import KeyframeGrouper
from wardmap.server.association.hdp import HdpConfig, HdpItem, HdpTopic, gibbs_associate
from wardmap.server.association.mot import KeyframeView, MotConfig, track_group
from wardmap.server.association.refine import RefineConfig, landmark_size, refine_index
from wardmap.server.association.spatial import SpatialGrid
from wardmap.server.association.types import Landmark, LandmarkChange
from wardmap.server.perception.types import ObjectMeasurement
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import GeometryError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.se3 import check_transform, inverse

__all__ = ["METHODS", "AssociationConfig", "Associator", "Method", "beyond_range"]

log = logging.getLogger(__name__)

_NO_DESCRIPTORS = np.zeros((0, 32), np.uint8)
_NO_HISTOGRAM = np.zeros(0, np.float32)

F64 = NDArray[np.float64]
Method = Literal["hierarchical", "per_keyframe_hdp", "nearest"]
METHODS: tuple[Method, ...] = ("hierarchical", "per_keyframe_hdp", "nearest")


@dataclass(frozen=True)
class AssociationConfig:
    """Association parameters (TOML table ``[association]``, example ``deploy/association.toml``)."""

    method: Method = "hierarchical"
    """``hierarchical`` (paper 000), ``per_keyframe_hdp`` (HDP-SLAM) or ``nearest``."""
    group_size: int = 6
    """M: keyframes per group (paper: usually fewer than 10)."""
    group_overlap: int = 2
    """j: keyframes shared by neighbouring groups."""
    seed: int = 0
    """Seed of the Gibbs sampler (group n draws from ``default_rng([seed, n])``)."""
    mot: MotConfig = field(default_factory=MotConfig)
    """In-group tracker (``[association.mot]``)."""
    hdp: HdpConfig = field(default_factory=HdpConfig)
    """Across-group HDP (``[association.hdp]``)."""
    refine: RefineConfig = field(default_factory=RefineConfig)
    """Eq. 4-6 pose refinement (``[association.refine]``)."""
    nearest: NearestConfig = field(default_factory=NearestConfig)
    """The ``nearest`` baseline (``[association.nearest]``)."""
    max_history: int = 100
    """A landmark's pose prior (Eq. 2-3), pose refinement (Eq. 4-6) and size use its most recent
    this many measurements (``keep_measurements`` says whether the older ones stay in memory).
    Eq. 4-6 compares every pair, so without a bound a robot that passes the same objects all
    day would slow association down without end (docs/decisions/0010). Beyond the paper."""
    merge_inside: float = 0.8
    """``hierarchical``: after each group, two landmarks of one class are merged when this share
    of the smaller one's world box (volume) lies inside the other's box; 0 never merges. Two
    objects cannot fill the same space, so such landmarks are one object the association
    split: fragments of it measured in the same keyframes (which can never share a landmark)
    or a part seen alone. The larger landmark (more measurements) takes the other's
    measurements, and :meth:`Associator.add_keyframe` reports the other as ``merged``. Beyond
    the paper (docs/decisions/0004)."""
    merge_fragments: float = 0.3
    """``hierarchical``: two landmarks of one class are also merged when this share of the
    smaller one's world box lies inside the other's and the box holding both fits the class's
    size bound (``HdpConfig.class_size_m``): together they are no larger than one object, so
    they are two parts of it (a chair's backrest cut off its seat in some views). Two
    neighbouring objects hardly overlap and together exceed the bound. 0 turns it off.
    Beyond the paper (docs/decisions/0004)."""
    merge_across: float = 0.5
    """``hierarchical``: the same for two landmarks of different classes, at this share; 0 never.
    The network calls part of an object by a neighbouring class now and then (the foot of a bed
    a cart, a wheelchair a chair, the edge of a door a cabinet), and landmarks never mix
    classes, so each confusion became a second landmark inside the first. The boxes compared
    here are hulls: a landmark's box grown over its recent measurements' boxes, within its
    class's size bound (a bed seen in parts has a median box of one part). Classes the
    knowledge graph relates (a cup ``placed_on`` a cart, a chair ``stands_beside`` a bed) are
    found together and never merged. The merged landmark takes the class most of its
    measurements were measured as. The box holding both hulls must fit the surviving class's
    size bound (``HdpConfig.class_size_m``): an IV pole in front of a sink is no part of a sink.
    Beyond the paper (docs/decisions/0004)."""
    merge_by_footprint: tuple[str, ...] = ("bed", "cabinet", "cart", "chair", "desk", "iv_pole", "wheelchair")
    """``hierarchical``: classes of objects that stand on the floor. For two landmarks of these
    classes the merge shares above are taken over their footprints (the horizontal overlap of
    their boxes or hulls) instead of their volumes; the box holding both must still fit the
    surviving class's size bound, height included. The network often finds only part of such an
    object in a view (a chair's legs, and its seat called a wheelchair; an IV pole's stand apart
    from its pole); those parts lie one above the other and barely overlap in volume, while two
    objects cannot stand on the same floor. Empty: volumes for every class. Beyond the paper
    (docs/decisions/0004)."""
    merge_within_m: tuple[tuple[str, float], ...] = (("chair", 0.35),)
    """``hierarchical``: ``(class, metres)`` pairs. Two landmarks of a listed class whose
    centres lie closer than this horizontally are merged as well: two objects of the class
    cannot stand that close (hospital chairs are at least 0.4 m wide, the simulator's 0.465 m).
    The shares above miss a chair whose views split between two landmarks when one of them
    holds masks that run onto the wall beside the chair: the box holding both is then wider
    than any chair. Empty: off. Beyond the paper (docs/decisions/0005)."""
    nearest_centre: bool = True
    """``hierarchical``: after each group, a measurement of the group of a class seen whole (a
    horizontal size bound under ``HdpConfig.parts_min_m``, or none: chairs, IV poles, cups)
    moves to the landmark of its class whose refined centre (Eq. 4-6) is nearest to it. A track
    of the in-group tracker follows a mask that slides along a row of identical chairs, and
    the whole track goes to one landmark; the refined centres, held by many measurements, do
    not slide. Large classes (beds, doors) are seen in parts, whose centres lie far from the
    object's, and keep the association's choice. Beyond the paper (docs/decisions/0002)."""
    nearest_held_share: float = 0.5
    """``hierarchical``, with ``nearest_centre``: the nearest refined centre is overruled by the
    measurement's own 3D points. When the box of the landmark with the nearest centre holds less
    than this share (0..1) of the points and the box of another landmark of the class within
    reach holds at least this share, the measurement goes to the one holding most. A mask that
    lies mostly over one chair of a row and partly over the next has its box centre between the
    two, often nearer the next one (the part on the next chair lies farther back, so it spans
    more metres per pixel); most of its points lie on the chair it belongs to. The boxes are the
    landmarks' own (refined pose and size), grown by ``held_margin_m``. 0: centres only. Beyond
    the paper (docs/decisions/0003)."""
    held_margin_m: float = 0.05
    """Growth of a landmark's box on every side for ``nearest_held_share``, metres: depth noise
    and a refined pose taken from one measurement put a surface point a few centimetres outside
    the box."""
    merge_fitting: tuple[str, ...] = ("chair",)
    """``hierarchical``: classes whose two landmarks are merged whenever the box holding both
    fits one object of the class (``HdpConfig.class_size_m``), however little they overlap. The
    network sometimes finds a chair's backrest and its seat and legs apart, and the two
    landmarks' boxes share no footprint, so ``merge_fragments`` keeps them apart; the box
    holding both is one chair. Two chairs of a row give a box wider than the class bound.
    Classes without a size bound are refused. Beyond the paper (docs/decisions/0005)."""
    size_percentile: float = 90.0
    """Every method but ``per_keyframe_hdp``: a landmark's height is this percentile (0..100) of
    its recent measurements' heights, and so are its horizontal extents for
    ``full_extent_classes``; the other horizontal extents are the median (:func:`landmark_size`).
    A view that sees less of an object measures it smaller, never larger (a chair's legs only, a
    bed cut by the image border), so the median of the sizes is short. 50: the median
    everywhere. Beyond the paper (docs/decisions/0001)."""
    full_extent_classes: tuple[str, ...] = ("bed", "cabinet", "cart", "desk", "sink", "wheelchair")
    """Classes whose horizontal extents take ``size_percentile`` as well: objects the network
    mostly sees in parts. Doors and wall monitors are left out because their masks spill onto
    the wall beside them, which a high percentile would count as width; chairs and IV poles
    are seen whole (docs/decisions/0001)."""
    completed_when_cut: tuple[str, ...] = ("door",)
    """Classes whose measurements count as whole views when their box touches the image border:
    the in-group tracker keeps ``MotConfig.max_distance_m`` for them and the GMM
    ``HdpConfig.sigma_position_m``, instead of the wider gate and sigma of a partly seen object.
    The perception completes a door cut by a side border to the usual door width beyond it
    (``[perception.measure] clipped_width_m``, doors), so its centre is where a whole door's is;
    a cut at the top or bottom (a door seen close by) moves the centre in height only, where the
    partial-view slack already allows for the shorter box. Keep it to the classes of
    ``clipped_width_m``. Empty: every border-touching view is partial. Beyond the paper
    (docs/decisions/0009)."""
    keep_measurements: bool = True
    """Keep every measurement of a landmark in memory (the offline runner writes them all to
    landmarks.json). False: only the most recent ``max_history`` (plus the first, for
    ``per_keyframe_hdp``), so memory stays bounded on a server that runs for months; its
    database has all of them and :attr:`Landmark.n_measurements` counts them."""
    confirm_classes: tuple[str, ...] = ("bed", "cabinet", "cart", "chair", "desk", "wheelchair")
    """Classes of objects that stand out from the walls and the floor. A landmark of one of them
    is confirmed (:attr:`Landmark.confirmed`) once one of its measurements shows it as such: a
    view not cut by the left or right image border (``HdpConfig.border_px``), or one deeper
    than ``flat_m``, and in either case no wider than the class's largest object
    (``HdpConfig.class_size_m``) nor, when whole, narrower than its smallest (``min_width_m``).
    The network takes a wall at the edge of the view, close by, for a cabinet now and then;
    such a landmark holds only flat slivers cut by the image border, and a real cabinet, bed or
    cart is soon seen whole or with depth. Unconfirmed landmarks stay in the association and in
    the database; the map's queries leave them out unless asked (``include_unconfirmed``).
    Empty: every landmark is confirmed. Beyond the paper (docs/decisions/0006)."""
    flat_m: float = 0.05
    """The depth (the shorter horizontal extent, ``ObjectMeasurement.size[1]``) up to which a
    measurement cut by the image border counts as flat, metres (see ``confirm_classes``)."""
    min_width_m: tuple[tuple[str, float], ...] = (("bed", 0.5), ("door", 0.5))
    """``(class, metres)``: a view clear of the left and right image borders shows an object's
    whole width, so it confirms a landmark of the class only when its larger horizontal extent
    (``ObjectMeasurement.size[:2]``) is at least this, about half the narrowest object of the
    class. A view cut by a side border cannot show the width and confirms as before
    (``confirm_classes``: deeper than ``flat_m``; other classes: always). A landmark of a listed
    class not in ``confirm_classes`` (doors) needs one such view too. For these classes and
    ``confirm_classes`` a view wider than the class's largest object (``HdpConfig.class_size_m``)
    holds parts of several and confirms nothing. The network takes a door frame or a strip of
    wall for a door or a bed, whole in view but too narrow. Chairs are not listed: a chair can
    be seen only as its legs. Empty: no lower bound. Beyond the paper (docs/decisions/0006)."""
    min_height_m: tuple[tuple[str, float], ...] = ()
    """``(class, metres)``: a view clear of the top and bottom image borders
    (``HdpConfig.border_px``) confirms a landmark of the class only when its height
    (``ObjectMeasurement.size[2]``) is at least this; a view cut at the top or bottom cannot
    show the height and is judged as before. A listed class needs such a view to be confirmed.
    For a site whose wall posters the network takes for doors: ``[["door", 1.0]]``. Off by
    default because it also unconfirms real doors seen once with only their upper part
    (docs/decisions/0007). Empty: no lower bound."""
    max_range_m: float = 6.0
    """Measurements whose centre lies farther than this along the camera axis
    (``T_camera_object`` z, metres) are not associated (:func:`beyond_range`; every method).
    Far views are the noisiest and the most often wrong (a corridor corner seen once from far
    taken for a cabinet, two neighbouring doors at a grazing view in one mask). They stay stored
    with their keyframe, and :attr:`Associator.beyond_range` counts them; an object enters the
    map once the robot sees it from nearer. A large value turns it off. Beyond the paper
    (docs/decisions/0008)."""

    def __post_init__(self) -> None:
        if self.max_history < 1:
            raise ValueError(f"max_history must be >= 1, got {self.max_history}")
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        for name in ("merge_inside", "merge_fragments", "merge_across"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1] (0: never merge), got {getattr(self, name)}")
        if self.group_size < 1 or not 0 <= self.group_overlap < self.group_size:
            raise ValueError(f"need group_size M >= 1 and 0 <= group_overlap j < M, got M = "
                             f"{self.group_size}, j = {self.group_overlap}")
        if not (self.flat_m >= 0.0 and np.isfinite(self.flat_m)):
            raise ValueError(f"flat_m must be a finite depth >= 0 m, got {self.flat_m}")
        if not self.max_range_m > 0.0:
            raise ValueError(f"max_range_m must be > 0 m, got {self.max_range_m}")
        if not 0.0 <= self.size_percentile <= 100.0:
            raise ValueError(f"size_percentile must be in [0, 100] (50: the median), "
                             f"got {self.size_percentile}")
        for key in ("min_width_m", "min_height_m"):
            _check_class_bounds(key, getattr(self, key))
        if not 0.0 <= self.nearest_held_share <= 1.0:
            raise ValueError(f"nearest_held_share must be in [0, 1] (0: off), got {self.nearest_held_share}")
        if not (self.held_margin_m >= 0.0 and np.isfinite(self.held_margin_m)):
            raise ValueError(f"held_margin_m must be a finite distance >= 0 m, got {self.held_margin_m}")
        for entry in self.merge_within_m:
            if (len(entry) != 2 or not isinstance(entry[0], str) or not isinstance(entry[1], (int, float))
                    or not (np.isfinite(entry[1]) and entry[1] > 0.0)):
                raise ValueError(f"merge_within_m entries are [class, metres > 0], got {entry!r}")

    def checked_classes(self) -> frozenset[str]:
        """Classes whose landmarks need a view that shows the object before they are confirmed
        (``confirm_classes``, ``min_width_m`` and ``min_height_m``)."""
        return (frozenset(self.confirm_classes) | {name for name, _ in self.min_width_m}
                | {name for name, _ in self.min_height_m})


def _check_class_bounds(key: str, entries: Sequence[tuple[str, float]]) -> None:
    """``entries`` are ``[class, metres >= 0]`` pairs, each class once.

    Raises:
        ValueError: naming ``key``.
    """
    for entry in entries:
        if (len(entry) != 2 or not isinstance(entry[0], str) or not isinstance(entry[1], (int, float))
                or not (np.isfinite(entry[1]) and entry[1] >= 0.0)):
            raise ValueError(f"{key} entries are [class, metres >= 0], got {entry!r}")
    names = [name for name, _ in entries]
    if len(set(names)) != len(names):
        raise ValueError(f"{key} lists a class twice: {', '.join(sorted(names))}")


_FIT_TOL_M = 1e-3  # hulls are clipped to their class's bound: leave room for rounding


def beyond_range(m: ObjectMeasurement, max_range_m: float) -> bool:
    """True when the centre of measurement ``m`` lies farther than ``max_range_m`` metres along
    its camera's axis (``AssociationConfig.max_range_m``)."""
    return float(m.T_camera_object[2, 3]) > max_range_m


@dataclass(eq=False)
class _LandmarkState:
    id: int
    category: str
    measurements: list[ObjectMeasurement] = field(default_factory=list)
    mids: list[int] = field(default_factory=list)
    keyframe_mids: dict[int, set[int]] = field(default_factory=dict)
    tables: int = 0
    count: int = 0  # measurements ever added (``measurements`` may hold only the recent ones)
    classes: dict[str, int] = field(default_factory=dict)  # measured class -> measurements ever added
    confidence_sum: float = 0.0
    first: ObjectMeasurement | None = None
    first_mid: int = -1
    T_world_object: F64 = field(default_factory=lambda: np.eye(4))
    size: F64 = field(default_factory=lambda: np.zeros(3))
    centre: F64 = field(default_factory=lambda: np.zeros(3))  # grid position
    solid: int = 0  # its measurements (ever, less those moved out) that show a standing object

    def add(self, mid: int, m: ObjectMeasurement, keyframe: int, history: int) -> None:
        """Append a measurement; keep ``keyframe_mids`` to the last ``history`` keyframes
        (keyframe indexes only grow, so the dict's first key is the oldest)."""
        self.measurements.append(m)
        self.mids.append(mid)
        self.count += 1
        self.classes[m.category] = self.classes.get(m.category, 0) + 1
        self.confidence_sum += float(m.confidence)
        if self.first is None:
            self.first, self.first_mid = m, mid
        self.keyframe_mids.setdefault(keyframe, set()).add(mid)
        while len(self.keyframe_mids) > history:
            del self.keyframe_mids[next(iter(self.keyframe_mids))]

    def remove(self, mid: int, keyframe: int) -> ObjectMeasurement:
        """Take measurement ``mid`` of ``keyframe`` out (it must be here, and not the only one);
        returns it."""
        k = self.mids.index(mid)
        m = self.measurements.pop(k)
        del self.mids[k]
        self.count -= 1
        self.classes[m.category] -= 1
        if not self.classes[m.category]:
            del self.classes[m.category]
        self.confidence_sum -= float(m.confidence)
        frame = self.keyframe_mids[keyframe]
        frame.discard(mid)
        if not frame:
            del self.keyframe_mids[keyframe]
        if mid == self.first_mid:
            self.first, self.first_mid = self.measurements[0], self.mids[0]
        return m

    def prune(self, history: int) -> list[int]:
        """Keep only the most recent ``history`` measurements; returns the dropped ids."""
        if len(self.mids) <= history:
            return []
        dropped = self.mids[:-history]
        del self.measurements[:-history], self.mids[:-history]
        return dropped

    def poses(self, history: int) -> F64:
        """(n, 4, 4) poses of the most recent ``history`` measurements, oldest first."""
        return np.stack([m.T_world_object for m in self.measurements[-history:]])

    def snapshot(self, checked: frozenset[str]) -> Landmark:
        """The landmark as reported; ``checked``: classes that need a confirming view."""
        conf = self.confidence_sum / max(self.count, 1)
        confirmed = self.solid > 0 or self.category not in checked
        return Landmark(self.id, self.category, self.T_world_object.copy(), self.size.copy(), conf,
                        tuple(self.measurements), self.count, confirmed)


def _check_measurements(measurements: Sequence[ObjectMeasurement]) -> None:
    for k, m in enumerate(measurements):
        if not isinstance(m, ObjectMeasurement):
            raise GeometryError(f"add_keyframe: measurement {k} is a {type(m).__name__}, not an "
                                "ObjectMeasurement")
        check_transform(m.T_world_object, f"measurement {k} T_world_object")
        if np.shape(m.size) != (3,) or np.shape(m.box_xyxy) != (4,):
            raise GeometryError(f"add_keyframe: measurement {k}: size must be (3,) and box_xyxy (4,), "
                                f"got {np.shape(m.size)} and {np.shape(m.box_xyxy)}")


@dataclass(eq=False)
class _Stream:
    """Keyframe grouping state of one robot session (local keyframe numbers 0, 1, ...)."""

    grouper: KeyframeGrouper
    views: dict[int, KeyframeView] = field(default_factory=dict)  # local number -> view
    next_local: int = 0


class Associator:
    """Incremental object association over keyframes (see the module docstring).

    Args:
        config: method and parameters.
        knowledge: the knowledge graph whose related classes are never merged across
            (``merge_across``); None loads the packaged one.
    """

    def __init__(self, config: AssociationConfig | None = None,
                 knowledge: KnowledgeGraph | None = None) -> None:
        self.config = config or AssociationConfig()
        cfg = self.config
        kg = knowledge or KnowledgeGraph.load()
        for key, listed in (("confirm_classes", cfg.confirm_classes),
                            ("min_width_m", [name for name, _ in cfg.min_width_m]),
                            ("min_height_m", [name for name, _ in cfg.min_height_m]),
                            ("merge_by_footprint", cfg.merge_by_footprint),
                            ("full_extent_classes", cfg.full_extent_classes),
                            ("completed_when_cut", cfg.completed_when_cut),
                            ("merge_within_m", [name for name, _ in cfg.merge_within_m]),
                            ("merge_fitting", cfg.merge_fitting)):
            unknown = sorted(set(listed) - set(kg.names))
            if unknown:
                raise ValueError(f"{key}: not knowledge-graph classes: {', '.join(unknown)}")
        unbounded = sorted(name for name in cfg.merge_fitting if cfg.hdp.class_extent(name) is None)
        if unbounded:
            raise ValueError(f"merge_fitting: classes without a size bound (hdp.class_size_m): "
                             f"{', '.join(unbounded)}")
        self._checked = cfg.checked_classes()
        self._min_width = dict(cfg.min_width_m)
        self._min_height = dict(cfg.min_height_m)
        self._together = {frozenset((r.subject, r.object)) for r in kg.relations()}
        self._on_floor = frozenset(cfg.merge_by_footprint)
        self._full_extent = frozenset(cfg.full_extent_classes)
        self._completed = frozenset(cfg.completed_when_cut)
        self._within = dict(cfg.merge_within_m)
        self._fitting = frozenset(cfg.merge_fitting)
        self._group_shape = (cfg.group_size, cfg.group_overlap) if cfg.method == "hierarchical" else (1, 0)
        self._streams: dict[str, _Stream] = {}
        self._next_keyframe = 0
        self._next_mid = 0
        self._next_id = 1
        self._groups_done = 0
        self._landmarks: dict[int, _LandmarkState] = {}
        self._owner: dict[int, int] = {}  # measurement id -> landmark id
        self._sigma: dict[int, float] = {}  # measurement id -> HDP position sigma (metres)
        self._extent: dict[int, F64] = {}  # measurement id -> world-axis extents (metres)
        self._box: dict[int, tuple[F64, F64]] = {}  # measurement id -> world-axis box corners (metres)
        self._solid: dict[int, bool] = {}  # measurement id -> confirms its landmark (_shows_object)
        # Measurement ids pruned from their landmark (max_history) while a stream's open group still
        # holds them (the overlap of the next group): their entries above stay until that group is done.
        self._retired: set[int] = set()
        radius = cfg.nearest.max_distance_m if cfg.method == "nearest" else cfg.hdp.candidate_radius_m
        self._grid = SpatialGrid(radius)
        # Merging looks this far: the largest candidate search radius of any class.
        self._merge_radius = max([cfg.hdp.candidate_radius_m]
                                 + [cfg.hdp.search_radius(name) for name, _, _ in cfg.hdp.class_size_m])
        self._poses_cache: dict[int, tuple[int, F64]] = {}  # id -> (measurements, recent poses)
        self._grown: set[int] = set()  # landmarks that gained measurements since the last _prune
        # In the current call: landmark -> measurements added; merged landmark -> (its last state
        # if reported before, else None; the landmark that took it).
        self._fresh: dict[int, list[ObjectMeasurement]] = {}
        self._merged: dict[int, tuple[Landmark | None, int]] = {}
        self.beyond_range = 0
        """Measurements given to :meth:`add_keyframe` and not associated: farther than
        ``AssociationConfig.max_range_m``."""

    # ------------------------------------------------------------------ public API

    def add_keyframe(
        self,
        measurements: Sequence[ObjectMeasurement],
        T_world_camera: ArrayLike,
        camera: PinholeCamera,
        *,
        stream: str = "",
    ) -> list[LandmarkChange]:
        """Add one keyframe's measurements; returns the landmarks this created or changed.

        Args:
            measurements: the keyframe's object measurements (may be empty); those farther
                than ``max_range_m`` are counted in :attr:`beyond_range` and left out.
            T_world_camera: (4, 4) the keyframe's camera pose in ``world``.
            camera: colour-camera intrinsics of the measurements' pixel boxes.
            stream: the keyframe sequence it belongs to (``"<robot>/<session>"`` on the
                server); keyframe groups never mix streams.

        Returns:
            ``created`` and ``updated`` changes in landmark-id order, then ``merged`` ones;
            empty while a ``hierarchical`` group is still filling up.

        Raises:
            GeometryError: a pose is not a rigid transform or a measurement is malformed.
        """
        T = check_transform(T_world_camera, "T_world_camera")
        if not isinstance(camera, PinholeCamera):
            raise GeometryError(f"add_keyframe: camera must be a PinholeCamera, got {type(camera).__name__}")
        _check_measurements(measurements)
        near = [m for m in measurements if not beyond_range(m, self.config.max_range_m)]
        self.beyond_range += len(measurements) - len(near)
        measurements = near
        self._prune()
        index = self._next_keyframe
        self._next_keyframe += 1
        mids = tuple(range(self._next_mid, self._next_mid + len(measurements)))
        self._next_mid += len(measurements)
        view = KeyframeView(index, T, camera, tuple(measurements), mids)
        hdp = self.config.hdp
        for mid, m in zip(mids, measurements, strict=True):
            partial = m.category not in self._completed and is_truncated(m.box_xyxy, camera, hdp.border_px)
            self._sigma[mid] = hdp.sigma_position_partial_m if partial else hdp.sigma_position_m
            self._solid[mid] = self._shows_object(m, cut_at_side(m.box_xyxy, camera, hdp.border_px),
                                                  cut_at_top_or_bottom(m.box_xyxy, camera, hdp.border_px))
            self._extent[mid] = world_extents(np.asarray(m.T_world_object), np.asarray(m.size))
            centre = np.asarray(m.T_world_object, dtype=np.float64)[:3, 3]
            self._box[mid] = (centre - self._extent[mid] / 2.0, centre + self._extent[mid] / 2.0)
        st = self._streams.get(stream)
        if st is None:
            st = self._streams[stream] = _Stream(KeyframeGrouper(*self._group_shape))
        local = st.next_local
        st.next_local += 1
        st.views[local] = view
        changed: dict[int, str] = {}
        if self.config.method == "nearest":
            self._nearest(view, changed)
        else:
            for group in st.grouper.push(local):
                self._hdp_group([st.views[k] for k in group], changed)
        for k in [k for k in st.views if k <= local - self.config.group_size]:
            del st.views[k]
        self._forget_retired()
        return self._changes(changed)

    def flush(self, stream: str | None = None) -> list[LandmarkChange]:
        """Associate the incomplete last group of ``stream`` (None: of every stream).

        Call it at the end of a run or robot session; the stream's next keyframe starts a
        new run of groups (no group spans a flush).
        """
        self._prune()
        changed: dict[int, str] = {}
        names = sorted(self._streams) if stream is None else [stream] if stream in self._streams else []
        for name in names:
            st = self._streams[name]
            for group in st.grouper.flush():
                self._hdp_group([st.views[k] for k in group], changed)
            st.views.clear()
        self._forget_retired()
        return self._changes(changed)

    def landmarks(self) -> list[Landmark]:
        """Snapshots of all landmarks, by id."""
        return [self._landmarks[k].snapshot(self._checked) for k in sorted(self._landmarks)]

    @property
    def pending_keyframes(self) -> int:
        """Keyframes added whose measurements are not yet in a landmark (wait for a group)."""
        return sum(1 for st in self._streams.values() for v in st.views.values()
                   if any(mid not in self._owner for mid in v.mids))

    # ------------------------------------------------------------------ internals

    def _changes(self, changed: dict[int, str]) -> list[LandmarkChange]:
        out = []
        for lid in sorted(changed):
            snap = self._landmarks[lid].snapshot(self._checked)
            added = tuple(self._fresh.get(lid, ()))
            out.append(LandmarkChange("created" if changed[lid] == "created" else "updated", snap, added))
        for lid in sorted(self._merged):
            last, into = self._merged[lid]
            while into not in self._landmarks:  # merged again later in this call
                into = self._merged[into][1]
            if last is not None:
                out.append(LandmarkChange("merged", last, into=into))
        self._fresh, self._merged = {}, {}
        return out

    def _new_landmark(self, category: str, changed: dict[int, str]) -> _LandmarkState:
        lm = _LandmarkState(self._next_id, category)
        self._landmarks[lm.id] = lm
        self._next_id += 1
        changed[lm.id] = "created"
        return lm

    def _add(self, lm: _LandmarkState, mid: int, m: ObjectMeasurement, keyframe: int) -> None:
        """Give measurement ``mid`` to ``lm``. Without ``keep_measurements`` the landmark keeps it
        without its appearance (ORB descriptors, colour histogram): only the in-group tracker
        compares appearance, on the keyframes' own measurements, and the two are most of a
        measurement's memory once the server has dropped masks and points (docs/decisions/0010).
        The change still reports ``m`` as given."""
        self._owner[mid] = lm.id
        kept = m if self.config.keep_measurements else \
            dataclasses.replace(m, descriptors=_NO_DESCRIPTORS, color_hist=_NO_HISTOGRAM)
        lm.add(mid, kept, keyframe, self.config.max_history)
        lm.solid += self._solid[mid]
        self._grown.add(lm.id)
        self._fresh.setdefault(lm.id, []).append(m)

    def _prune(self) -> None:
        """Without ``keep_measurements``: landmarks that grew since the last call drop all but their
        most recent ``max_history`` measurements. Called before each update, so the changes an
        update returns still carry every measurement it added."""
        if not self.config.keep_measurements:
            for lid in self._grown:
                lm = self._landmarks[lid]
                for old in lm.prune(self.config.max_history):
                    if old != lm.first_mid:  # per_keyframe_hdp's topic is the first measurement
                        self._retired.add(old)
            self._forget_retired()
        self._grown.clear()

    def _forget_retired(self) -> None:
        """Drop the entries of pruned measurement ids that no open group of any stream holds any
        more (another robot can fill a landmark's history while this one's group is still open)."""
        if not self._retired:
            return
        pending = {mid for st in self._streams.values() for v in st.views.values() for mid in v.mids}
        for old in self._retired - pending:
            del self._owner[old], self._sigma[old], self._extent[old], self._box[old]
            del self._solid[old]
        self._retired &= pending

    def _mark(self, lid: int, changed: dict[int, str]) -> None:
        changed.setdefault(lid, "updated")

    def _update_pose(self, lm: _LandmarkState) -> None:
        if self.config.method == "per_keyframe_hdp":
            first = lm.first  # HDP-SLAM: the first measurement (maybe older than the history)
            assert first is not None
            lm.T_world_object = np.asarray(first.T_world_object, dtype=np.float64).copy()
            lm.size = np.asarray(first.size, dtype=np.float64).copy()
            lm.centre = lm.T_world_object[:3, 3].copy()
        else:
            poses = self._poses_of(lm)
            if self.config.method == "nearest":
                lm.centre = poses[:, :3, 3].mean(axis=0)
                k = int(np.argmin(np.linalg.norm(poses[:, :3, 3] - lm.centre, axis=1)))
            else:
                k = refine_index(poses, self.config.refine)  # Eq. 4-6
                lm.centre = poses[k, :3, 3].copy()
            lm.T_world_object = poses[k].copy()
            recent = lm.measurements[-self.config.max_history:]
            lm.size = landmark_size(np.stack([m.size for m in recent]), self.config.size_percentile,
                                    lm.category in self._full_extent)
        self._grid.put(lm.id, lm.centre)

    def _poses_of(self, lm: _LandmarkState) -> F64:
        """Poses of the landmark's most recent ``max_history`` measurements (cached)."""
        n = lm.count
        cached = self._poses_cache.get(lm.id)
        if cached is None or cached[0] != n:
            cached = (n, lm.poses(self.config.max_history))
            self._poses_cache[lm.id] = cached
        return cached[1]

    def _nearest(self, view: KeyframeView, changed: dict[int, str]) -> None:
        ms = view.measurements
        if not ms:
            return
        positions = np.stack([m.T_world_object[:3, 3] for m in ms])
        radius = self.config.nearest.max_distance_m
        near: dict[int, tuple[int, str, F64]] = {}
        for p in positions:
            for lid in self._grid.query(p, radius):
                lm = self._landmarks[lid]
                near[lid] = (lid, lm.category, lm.centre)
        assignment = nearest_assign([m.category for m in ms], positions, list(near.values()),
                                    self.config.nearest)
        touched = []
        for m, mid, target in zip(ms, view.mids, assignment, strict=True):
            lm = self._new_landmark(m.category, changed) if target is None else self._landmarks[target]
            self._add(lm, mid, m, view.index)
            lm.tables += 1
            self._mark(lm.id, changed)
            touched.append(lm)
        for lm in touched:
            self._update_pose(lm)

    def _to_nearest_centre(self, added: list[tuple[int, ObjectMeasurement, int]],
                           touched: dict[int, _LandmarkState], changed: dict[int, str]) -> None:
        """Move each measurement of ``added`` (id, measurement, keyframe: what this group added)
        of a class seen whole to the landmark of its class with the nearest centre
        (``AssociationConfig.nearest_centre``), or to the one whose box holds most of its points
        (``nearest_held_share``, :meth:`_holder`). No landmark is left empty: its last
        measurement stays."""
        hdp = self.config.hdp
        moves: list[tuple[int, int, ObjectMeasurement, _LandmarkState, _LandmarkState]] = []
        leaving: Counter[int] = Counter()
        for mid, m, keyframe in added:
            if hdp.seen_in_parts(m.category):
                continue
            owner = self._landmarks[self._owner[mid]]
            p = m.T_world_object[:3, 3]
            best, best_d = owner, float(np.linalg.norm(owner.centre - p))
            near = [self._landmarks[lid] for lid in self._grid.query(p, hdp.search_radius(m.category))]
            near = [lm for lm in near if lm.category == m.category and lm is not owner]
            for lm in near:
                d = float(np.linalg.norm(lm.centre - p))
                if d < best_d:
                    best, best_d = lm, d
            if self.config.nearest_held_share > 0:
                best = self._holder(m, best, [owner, *near])
            if best is not owner and len(owner.mids) - leaving[owner.id] > 1:
                leaving[owner.id] += 1
                moves.append((mid, keyframe, m, owner, best))
        for mid, keyframe, m, src, dst in moves:
            src.remove(mid, keyframe)
            src.solid -= self._solid[mid]
            self._fresh[src.id].remove(m)  # the measurement as given (the landmark's may be slimmed)
            self._add(dst, mid, m, keyframe)
            self._mark(dst.id, changed)
            touched[dst.id] = dst
        for lm in {x.id: x for _, _, _, a, b in moves for x in (a, b)}.values():
            self._poses_cache.pop(lm.id, None)  # same count, other measurements
            self._update_pose(lm)

    def _holder(self, m: ObjectMeasurement, nearest: _LandmarkState,
                candidates: Sequence[_LandmarkState]) -> _LandmarkState:
        """``nearest``, unless its box holds less than ``nearest_held_share`` of ``m``'s 3D points
        and the box of one of ``candidates`` holds at least that share: then the candidate
        holding most. Boxes are the landmarks' (pose and size) grown by ``held_margin_m``."""
        if len(m.points_camera) == 0:
            return nearest
        T = m.T_world_camera
        points = m.points_camera.astype(np.float64) @ T[:3, :3].T + T[:3, 3]  # (N, 3) world
        margin, least = self.config.held_margin_m, self.config.nearest_held_share

        def share(lm: _LandmarkState) -> float:
            local = (points - lm.T_world_object[:3, 3]) @ lm.T_world_object[:3, :3]
            return float(np.mean(np.all(np.abs(local) <= lm.size / 2.0 + margin, axis=1)))

        if share(nearest) >= least:
            return nearest
        best, most = nearest, least
        for lm in candidates:
            if lm is not nearest and (held := share(lm)) >= most:
                best, most = lm, held
        return best

    def _bounds(self, lm: _LandmarkState) -> tuple[F64, F64]:
        """World-axis box (lower and upper corner, (3,) each) of a landmark, metres."""
        half = world_extents(lm.T_world_object, lm.size) / 2.0
        return lm.centre - half, lm.centre + half

    def _hull(self, lm: _LandmarkState) -> tuple[F64, F64]:
        """World-axis box holding its box and the boxes of its recent measurements, clipped to its
        class's size bound about its centre (lower and upper corner, (3,) each), metres."""
        lo, hi = self._bounds(lm)
        boxes = [self._box[mid] for mid in lm.mids[-self.config.max_history:]]
        lo_m, hi_m = np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)
        bound = self.config.hdp.class_extent(lm.category)
        if bound is not None:
            lo_m, hi_m = np.maximum(lo_m, lm.centre - bound / 2.0), np.minimum(hi_m, lm.centre + bound / 2.0)
        return np.minimum(lo, lo_m), np.maximum(hi, hi_m)

    def _shows_object(self, m: ObjectMeasurement, cut: bool, cut_height: bool) -> bool:
        """True when measurement ``m`` confirms a landmark (``confirm_classes``, ``min_width_m``,
        ``min_height_m``); ``cut``: its box reaches the left or right image border
        (:func:`cut_at_side`); ``cut_height``: the top or bottom one."""
        cfg, category, width = self.config, m.category, float(max(m.size[0], m.size[1]))
        if category not in self._checked:
            return True
        bound = cfg.hdp.class_extent(category)
        if bound is not None and width > float(bound[0]):
            return False  # wider than any object of the class: parts of several
        lowest = self._min_height.get(category)
        if lowest is not None and not cut_height and float(m.size[2]) < lowest:
            return False  # whole height in view, and too low for the class
        if cut:
            return category not in cfg.confirm_classes or float(m.size[1]) > cfg.flat_m
        least = self._min_width.get(category)
        return least is None or width >= least

    def _fits(self, category: str, a: tuple[F64, F64], b: tuple[F64, F64]) -> bool:
        """True when the world-axis box holding boxes ``a`` and ``b`` fits the size bound of
        ``category`` (``HdpConfig.class_size_m``; no bound: True)."""
        bound = self.config.hdp.class_extent(category)
        if bound is None:
            return True
        extent = np.maximum(a[1], b[1]) - np.minimum(a[0], b[0])
        return bool(np.all(extent <= bound + _FIT_TOL_M))

    def _merge_overlapping(self, lids: list[int], changed: dict[int, str]) -> None:
        """Merge each of ``lids`` with a landmark whose box holds ``merge_inside`` of the smaller
        one's, or ``merge_fragments`` when both fit one object of the class (any share for a
        ``merge_fitting`` class), or whose centre lies
        within ``merge_within_m`` of its own (for another class:
        whose hull holds ``merge_across`` of the smaller hull; footprints instead of volumes for
        two ``merge_by_footprint`` classes; see :class:`AssociationConfig`); repeated for the
        landmark that grew."""
        cfg = self.config
        queue = list(lids)
        while queue:
            lm = self._landmarks.get(queue.pop())
            if lm is None:
                continue
            box, hull, within = self._bounds(lm), None, self._within.get(lm.category, 0.0)
            for oid in sorted(self._grid.query(lm.centre, self._merge_radius)):
                other = self._landmarks[oid]
                if oid == lm.id:
                    continue
                same = other.category == lm.category
                if same:
                    share, (lo, hi), (olo, ohi) = cfg.merge_inside, box, self._bounds(other)
                elif cfg.merge_across > 0 and frozenset((lm.category, other.category)) not in self._together:
                    hull = hull or self._hull(lm)
                    share, (lo, hi), (olo, ohi) = cfg.merge_across, hull, self._hull(other)
                else:
                    continue
                # Floor-standing objects: footprints (x, y); otherwise volumes.
                axes = 2 if lm.category in self._on_floor and other.category in self._on_floor else 3
                common = np.minimum(hi, ohi)[:axes] - np.maximum(lo, olo)[:axes]
                inside = float(np.prod(np.clip(common, 0.0, None)))
                smaller = min(float(np.prod((hi - lo)[:axes])), float(np.prod((ohi - olo)[:axes])))
                held = share > 0 and inside >= share * smaller
                # parts of one object: both fit it, with merge_fragments overlap (any for merge_fitting)
                enough = lm.category in self._fitting or (
                    cfg.merge_fragments > 0 and inside >= cfg.merge_fragments * smaller)
                parts = same and enough and self._fits(lm.category, (lo, hi), (olo, ohi))
                close = same and float(np.linalg.norm((lm.centre - other.centre)[:2])) < within
                if not (held or parts or close):
                    continue
                keep, gone = (lm, other) if (lm.count, -lm.id) >= (other.count, -other.id) else (other, lm)
                if not same and not self._fits(keep.category, (lo, hi), (olo, ohi)):
                    continue
                self._absorb(keep, gone, changed)
                queue.append(keep.id)
                break

    def _absorb(self, keep: _LandmarkState, gone: _LandmarkState, changed: dict[int, str]) -> None:
        """Move every measurement of ``gone`` to ``keep`` and delete ``gone``."""
        reported = changed.get(gone.id) != "created"  # the caller holds it: report the merge
        self._merged[gone.id] = (gone.snapshot(self._checked) if reported else None, keep.id)
        self._fresh.setdefault(keep.id, []).extend(self._fresh.pop(gone.id, []))
        changed.pop(gone.id, None)
        pairs = sorted(zip(keep.mids + gone.mids, keep.measurements + gone.measurements, strict=True),
                       key=lambda pair: pair[0])
        keep.mids = [mid for mid, _ in pairs]
        keep.measurements = [m for _, m in pairs]
        for mid in gone.mids:
            self._owner[mid] = keep.id
        frames = dict(gone.keyframe_mids)
        for k, mids in keep.keyframe_mids.items():
            frames[k] = frames.get(k, set()) | mids
        keep.keyframe_mids = {k: frames[k] for k in sorted(frames)[-self.config.max_history:]}
        keep.count += gone.count
        keep.solid += gone.solid
        for name, n in gone.classes.items():
            keep.classes[name] = keep.classes.get(name, 0) + n
        # Across classes: the class most of its measurements were measured as (ties: its own).
        keep.category = max(keep.classes, key=lambda c: (keep.classes[c], c == keep.category))
        keep.confidence_sum += gone.confidence_sum
        keep.tables += gone.tables
        if gone.first is not None and gone.first_mid < keep.first_mid:
            keep.first, keep.first_mid = gone.first, gone.first_mid
        del self._landmarks[gone.id]
        self._grid.remove(gone.id)
        self._poses_cache.pop(gone.id, None)
        self._grown.discard(gone.id)
        self._grown.add(keep.id)
        self._mark(keep.id, changed)
        self._update_pose(keep)

    def _covisible(self, lm: _LandmarkState, views: Sequence[KeyframeView]) -> bool:
        """True when the landmark's box is (partly) in the image, grown by a margin, of one of the views.

        For a class with a size bound (``HdpConfig.class_size_m``) the box is grown to it: a bed
        seen so far only at its foot end is still co-visible from where its head end shows.
        """
        cfg = self.config.hdp
        bound = cfg.class_extent(lm.category)
        size = lm.size if bound is None else np.maximum(lm.size, bound)
        for v in views:
            T_cw = inverse(v.T_world_camera)
            centre = T_cw[:3, :3] @ lm.centre + T_cw[:3, 3]
            if np.linalg.norm(centre) > cfg.covisibility_max_depth_m:
                continue
            box = project_box(lm.T_world_object, size, v.T_world_camera, v.camera,
                              margin_px=cfg.covisibility_margin_px)
            if box is not None:
                return True
        return False

    def _topic(self, lm: _LandmarkState) -> HdpTopic:
        if self.config.method == "per_keyframe_hdp":
            assert lm.first is not None
            poses = lm.first.T_world_object[None].astype(np.float64)  # HDP-SLAM: the first
            mids = [lm.first_mid]
        else:
            poses = self._poses_of(lm)
            mids = lm.mids[-len(poses):]
        kf = {k: frozenset(v) for k, v in lm.keyframe_mids.items()}
        sigmas = np.array([self._sigma[mid] for mid in mids])
        extents = np.stack([self._extent[mid] for mid in mids])
        return HdpTopic(lm.id, lm.category, poses, lm.tables, kf, sigmas, extents)

    def _hdp_group(self, views: list[KeyframeView], changed: dict[int, str]) -> None:
        cfg = self.config
        if cfg.method == "hierarchical":
            group_landmarks = track_group(views, cfg.mot, cfg.hdp.class_extent, self._completed)
            items = [HdpItem(g.category, g.poses, tuple(g.keyframes), tuple(g.mids),
                             np.array([self._sigma[mid] for mid in g.mids]),
                             np.stack([self._extent[mid] for mid in g.mids])) for g in group_landmarks]
            measurements = [list(g.measurements) for g in group_landmarks]
            likelihood: Literal["gmm", "first_pose"] = "gmm"
        else:
            items = [dataclasses.replace(it, sigmas=np.array([self._sigma[it.mids[0]]]),
                                         extents=self._extent[it.mids[0]][None])
                     for v in views for it in per_keyframe_items(v)]
            measurements = [[m] for v in views for m in v.measurements]
            likelihood = "first_pose"
        group_no = self._groups_done
        self._groups_done += 1
        if not items:
            return
        topic_cache: dict[int, HdpTopic] = {}
        candidates: list[list[HdpTopic]] = []
        for it in items:
            centre = it.poses[refine_index(it.poses, cfg.refine), :3, 3]
            cands = []
            for lid in self._grid.query(centre, cfg.hdp.search_radius(it.category)):
                lm = self._landmarks[lid]
                if lm.category != it.category or not self._covisible(lm, views):
                    continue
                if lid not in topic_cache:
                    topic_cache[lid] = self._topic(lm)
                cands.append(topic_cache[lid])
            candidates.append(cands)
        rng = np.random.default_rng([cfg.seed, group_no])
        boxes = self._box if cfg.method == "hierarchical" else None  # HDP-SLAM: one per keyframe
        assignment = gibbs_associate(items, candidates, cfg.hdp, rng=rng, likelihood=likelihood, boxes=boxes)
        new_ids: dict[int, _LandmarkState] = {}
        touched: dict[int, _LandmarkState] = {}
        added: list[tuple[int, ObjectMeasurement, int]] = []
        for it, ms, target in zip(items, measurements, assignment, strict=True):
            fresh = [(mid, m, k) for mid, m, k in zip(it.mids, ms, it.keyframes, strict=True)
                     if mid not in self._owner]
            if target > 0:
                lm = self._landmarks[target]
            elif target in new_ids:
                lm = new_ids[target]
            elif fresh:
                lm = self._new_landmark(it.category, changed)
                new_ids[target] = lm
            else:
                continue  # only measurements already in landmarks: nothing to create
            lm.tables += 1
            for mid, m, k in fresh:
                self._add(lm, mid, m, k)
            added += fresh
            if fresh:
                self._mark(lm.id, changed)
                touched[lm.id] = lm
        for lm in touched.values():
            self._update_pose(lm)
        if cfg.method == "hierarchical" and cfg.nearest_centre:
            self._to_nearest_centre(added, touched, changed)
        if cfg.method == "hierarchical" and (max(cfg.merge_inside, cfg.merge_fragments, cfg.merge_across) > 0
                                             or self._within or self._fitting):
            self._merge_overlapping(list(touched), changed)
        log.debug("group %d: %d group landmarks -> %d landmarks touched (%d new)", group_no, len(items),
                  len(touched), len(new_ids))
