"""Server perception settings (``[perception]`` table, ``deploy/perception.toml``).

:class:`PerceptionConfig` holds the segmenter spec and the settings of every step of
:func:`~wardmap.server.perception.keyframe.measure_keyframe`: the segmenter's own
(``models.py``), the instance split (``instances.py``), the floor checks (``floor.py``) and
the 3D measurement (``[perception.measure]``, ``measure.py``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from wardmap.server.perception.measure import MeasureConfig
from wardmap.server.perception.types import CLASS_SIZE_M
from wardmap.shared.config import load_config
from wardmap.shared.detection import MaskConfig
from wardmap.shared.errors import ConfigError

__all__ = ["PerceptionConfig", "load_perception_config", "measure_config_for"]

_FLOOR_STANDING = ("bed", "cabinet", "desk", "cart", "wheelchair", "chair", "iv_pole")
"""Classes that stand on the floor, so their top height above it is bounded
(``PerceptionConfig.max_top_m``)."""


_ON_FLOOR_BODY = tuple(name for name in _FLOOR_STANDING if name != "iv_pole")
"""Floor-standing classes whose body rises from the floor, so their top is bounded from below
too (``PerceptionConfig.min_top_m``); not IV poles, of which the network may find only the base."""


@dataclass(frozen=True)
class PerceptionConfig:
    """Server perception parameters (``[perception]`` table, ``deploy/perception.toml``)."""

    segmenter: str = "model"
    """Segmenter spec: ``model``, ``model:PATH``, ``yolox:PATH`` or a path (module docstring)."""
    threads: int = 1
    """CPU threads of the network (onnxruntime ``intra_op_num_threads``)."""
    flip_average: bool = True
    """Segmentation network: run it on the image and on its mirror image and average the two
    logit maps (test-time augmentation; twice the network time). The network was trained on
    flipped crops, so both views are as good and their errors partly cancel. Shipped model,
    benchmark frames (seed 1001): mIoU 67.5 -> 69.1 %, every class up; validation worlds
    (seed 1000): 62.5 -> 63.6 %, frames on robot trajectories 68.8 -> 70.8 %."""
    refine_edges: bool = True
    """Segmentation network: a pixel on a class boundary takes its class from the bilinearly
    upsampled logits instead of its nearest network cell (``upsample_classes`` in
    ``wardmap.shared.segmentation``; exact where a pixel's four cells agree, so only boundary
    pixels are computed, about 3 ms a frame). Shipped model, benchmark frames (seed 1001):
    mIoU +0.25 points, every class up or equal. The class map only: instances are cut from
    the nearest cells' classes, as before (with the refined masks the association's object
    counts fell, docs/perception.md)."""
    placement_check: bool = True
    """Segmentation network: a region of a class the knowledge graph places on furniture
    (``placed_on``: cups and temperature guns on desks, cabinets, carts) that touches neither
    such furniture nor a person who carries it takes its next most likely class
    (``PlacementRule``, docs/perception.md). The shipped network paints cups and temperature
    guns on a sink's tap in the robot's views."""
    min_region_confidence: float = 0.35
    """Segmentation network: a connected region of a class (not background) whose mean
    softmax confidence is lower takes its cells' next most likely classes, checked again until
    none is vetoed, before the placement check (``drop_unsure_regions``, docs/perception.md;
    chosen on the validation worlds). 0 turns it off."""
    min_pixels: int = 400
    """Instances with fewer pixels are left out."""
    depth_jump_m: float = 0.15
    """Depth step that splits one class region into two instances (segmentation network)."""
    depth_jump_relative: float = 0.05
    """... as a fraction of depth, when larger."""
    min_confidence: float = 0.7
    """Segmentation network: instances whose mean softmax confidence is lower are left out
    (on held-out seed-1002 worlds, 0.7 with ``min_pixels`` 400 raised the share of instances
    on a real object from 57 % to 78 % and kept 70 % of those)."""
    trim_classes: tuple[str, ...] = ("wheelchair", "cart", "iv_pole", "chair", "bed", "sink", "cabinet")
    """Segmentation network: classes whose regions lose the pixels on the wall and floor
    planes around them and split into the pieces that remain
    (``instances.off_background_planes``). The network's masks bleed onto the wall, which
    joins a row of chairs into one region. On held-out seed-1002 worlds the share of
    measurements on a real object went from 80.6 % to 90.1 % (chairs on ward_chairs: 67 of 170
    to 455 of 552). Cabinets: seen along a corridor wall, their masks run onto the wall beside
    them; trimmed, the cabinet centroid median on seeds 1001 / 1002 / 1003 went 23.5 / 20.6 /
    15.1 -> 17.8 / 14.5 / 11.3 cm; over 35 association sequences counts equal to ground truth
    went 21 -> 20 and better than both baselines stayed 23. Not for classes flush with a wall
    (doors, wall monitors): trimming doors too (kept whole when trimming left under half,
    pieces kept as one instance) brought the door centroid to 7.8 / 8.3 / 8.0 cm, but the
    masks of two neighbouring doors then came apart in some keyframes and not in others, and
    counts equal fell 21 -> 17 (docs/perception.md)."""
    split_width_m: tuple[tuple[str, float], ...] = (("chair", 0.5), ("door", 1.4))
    """Segmentation network: ``[class, width]`` pairs. An instance of the class as wide as two
    or more objects of ``width`` metres is cut into side-by-side pieces
    (``instances.split_side_by_side``, needs the camera, so it runs where instances are
    measured). Touching chairs in a row stay one region after trimming (a chair: 0.45-0.55 m;
    0.5 cuts a region from 0.75 m, a mask over one and a half chairs, which 0.6 left whole and
    whose measurement sat between two chairs: on the tuning worlds association accuracy 92.2 ->
    94.6 %, chairs without a landmark of their own 5 -> 1);
    the network's mask runs over the 0.4 m of wall between two neighbouring doors (a door
    leaf is at most 1.3 m, so a door region of 2.1 m or more holds two). A class with a usual
    width in ``measure.clipped_width_m`` (doors) is first cut at the gaps below its top line and,
    when its mask reaches a side border of the image, from its far end in steps of that width
    (``usual_width_m`` of ``split_side_by_side``; docs/perception.md, "Instances")."""
    stack_gap_m: tuple[tuple[str, float], ...] = (("chair", 0.1), ("iv_pole", 1.0))
    """Segmentation network: ``[class, gap]`` pairs. Pieces of the class one above the other
    with at most ``gap`` metres between them are joined (``instances.merge_stacked``): a
    chair's open back and its seat; an IV pole's bag and its base, the thin pole between
    them unsegmented."""
    floor_gap_m: tuple[tuple[str, float], ...] = (("chair", 0.6),)
    """``[class, gap]`` pairs of floor-standing classes. An instance of the class whose lowest
    point is more than ``gap`` metres above the floor, with the wall or floor in plain view
    right below it, is not that object and is left out (``instances.floating_above_floor``;
    every segmenter). Only where the floor is known: keyframes of a robot base
    (``T_odom_base``), data sets with a ``[base]`` calibration. The network takes the red
    fire extinguishers on the simulator's walls for red chairs: on the tuning worlds (seed
    1002) 36 of the 68 chair measurements on no object floated, against 2 of 1,773 on a
    chair, and association accuracy went 96.58 -> 97.43 % with 8 fewer landmarks. Doors,
    cabinets, IV poles and wheelchairs are not in it: true ones float too often (a door
    whose lower part is cut off, an IV pole whose thin lower pole is missed)."""
    max_top_m: tuple[tuple[str, float], ...] = tuple(
        (name, height) for name, _, height in CLASS_SIZE_M if name in _FLOOR_STANDING
    )
    """``[class, top]`` pairs of floor-standing classes: no object of the class reaches higher
    than ``top`` metres above the floor (the heights in ``types.CLASS_SIZE_M``). An instance of
    the class whose pixels lie on a surface that goes on, without a step in depth, above the
    mask to more than ``top`` + 0.3 m is a piece of a wall and is left out
    (``instances.part_of_taller_surface``; every segmenter, where the floor is known). The
    network now and then takes a strip of corridor wall at the image border for a cabinet;
    above a real cabinet the camera sees the wall behind it, 0.5 m further away. On the
    association bench's worlds (seeds 1001-1005, 35 sequences, model measurements) it left
    out 14 cabinet measurements, 13 of them on no object; landmark counts and "better than
    both" stayed the same. Doors are not in it: a door is flush with the wall above it."""
    min_top_m: tuple[tuple[str, float], ...] = tuple((name, 0.2) for name in _ON_FLOOR_BODY)
    """``[class, top]`` pairs of floor-standing classes: every object of the class reaches at
    least ``top`` metres above the floor. An instance of the class whose top lies lower is
    left out (``instances.flat_on_floor``; every segmenter, where the floor is known). The
    network calls the dark gap under a bed's footboard a cart now and then: in the demo's
    ward (seed 0) it became a cart 6 cm tall on the map, 16 m from any cart. Objects of these
    classes stand 0.4 m tall or more (0.93 m or more in the simulator's worlds). IV poles are
    not in it (the network may find only a pole's base), nor doors and sinks (they do not
    stand on the floor). On the association bench's worlds (seeds 1001-1005, 35 sequences)
    it left out 103 network instances, each on an object of another class (96 "carts" on the
    low part of beds); the landmark counts' summed error went 28 -> 27, the rest stayed."""
    score_threshold: float = 0.3
    """YOLOX: smallest detection score used."""
    nms_iou: float = 0.45
    """YOLOX: per-class non-maximum suppression IoU."""
    measure: MeasureConfig = field(default_factory=MeasureConfig)
    """3D measurement parameters (``[perception.measure]``)."""
    detector_cluster_gap_m: float = 0.05
    """``yolox:`` segmenters: a box-based mask takes in things around the object, so its
    measurement keeps the largest 3D piece with this gap (``MeasureConfig.cluster_gap_m``)
    unless ``[perception.measure] cluster_gap_m`` is set; 0 turns it off."""
    masks: MaskConfig = field(default_factory=MaskConfig)
    """YOLOX: depth-based instance masks inside boxes (``[perception.masks]``)."""

    def __post_init__(self) -> None:
        if self.threads < 1:
            raise ConfigError(f"PerceptionConfig: threads must be >= 1, got {self.threads}")
        if self.min_pixels < 1:
            raise ConfigError(f"PerceptionConfig: min_pixels must be >= 1, got {self.min_pixels}")
        if self.depth_jump_m <= 0 or self.depth_jump_relative < 0:
            raise ConfigError("PerceptionConfig: need depth_jump_m > 0 and depth_jump_relative >= 0")
        for key in ("split_width_m", "stack_gap_m", "floor_gap_m", "max_top_m", "min_top_m"):
            for name, value in getattr(self, key):
                if not value > 0:
                    raise ConfigError(f"PerceptionConfig: {key} of {name!r} must be > 0, got {value}")
        if self.detector_cluster_gap_m < 0:
            raise ConfigError(
                f"PerceptionConfig: detector_cluster_gap_m must be >= 0, got {self.detector_cluster_gap_m}"
            )
        for name in ("score_threshold", "nms_iou", "min_confidence", "min_region_confidence"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"PerceptionConfig: {name} must lie in 0..1, got {getattr(self, name)!r}")


def load_perception_config(path: str | Path | None) -> PerceptionConfig:
    """The ``[perception]`` table of a TOML file (defaults when ``path`` is None).

    Raises:
        ConfigError: missing file, malformed TOML, unknown key or bad value (named).
    """
    return load_config(PerceptionConfig, path, section="perception")


def measure_config_for(config: PerceptionConfig, spec: str) -> MeasureConfig:
    """The measurement parameters for segmenter ``spec``: ``config.measure``, with
    ``detector_cluster_gap_m`` as the cluster gap for a ``yolox:`` detector when none is set."""
    m = config.measure
    if spec.strip().startswith("yolox:") and m.cluster_gap_m == 0 and config.detector_cluster_gap_m > 0:
        return dataclasses.replace(m, cluster_gap_m=config.detector_cluster_gap_m)
    return m
