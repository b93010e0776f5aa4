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
    flipped crops, so both views are as good and their errors partly cancel."""
    refine_edges: bool = True
    """Segmentation network: a pixel on a class boundary takes its class from the bilinearly
    upsampled logits instead of its nearest network cell (``upsample_classes`` in
    ``wardmap.shared.segmentation``; exact where a pixel's four cells agree, so only boundary
    pixels are computed). The class map only: instances are cut from the nearest cells'
    classes, whose boundaries do not straddle depth edges."""
    placement_check: bool = True
    """Segmentation network: a region of a class the knowledge graph places on furniture
    (``placed_on``: cups and temperature guns on desks, cabinets, carts) that touches neither
    such furniture nor a person who carries it takes its next most likely class
    (``PlacementRule``, docs/perception.md): a cup painted on a sink's tap is no cup."""
    min_region_confidence: float = 0.35
    """Segmentation network: a connected region of a class (not background) whose mean
    softmax confidence is lower takes its cells' next most likely classes, checked again until
    none is vetoed, before the placement check (``drop_unsure_regions``, docs/perception.md).
    0 turns it off."""
    min_pixels: int = 400
    """Instances with fewer pixels are left out."""
    depth_jump_m: float = 0.15
    """Depth step that splits one class region into two instances (segmentation network)."""
    depth_jump_relative: float = 0.05
    """... as a fraction of depth, when larger."""
    min_confidence: float = 0.7
    """Segmentation network: instances whose mean softmax confidence (0..1) is lower are left
    out: the ragged fringes a network leaves where it hesitates between classes."""
    trim_classes: tuple[str, ...] = ("wheelchair", "cart", "iv_pole", "chair", "bed", "sink", "cabinet")
    """Segmentation network: classes whose regions lose the pixels on the wall and floor
    planes around them and split into the pieces that remain
    (``instances.off_background_planes``). The network's masks bleed onto the wall, which
    joins a row of chairs into one region and runs a cabinet's mask along a corridor wall.
    Not for classes flush with a wall (doors, wall monitors): their pixels lie on the wall's
    plane, so trimming cuts into the object itself."""
    split_width_m: tuple[tuple[str, float], ...] = (("chair", 0.5), ("door", 1.4))
    """Segmentation network: ``[class, width]`` pairs, metres. An instance of the class as wide
    as two or more objects of ``width`` is cut into side-by-side pieces
    (``instances.split_side_by_side``): touching chairs in a row stay one region after
    trimming (a chair is 0.45-0.55 m wide), and the network's mask runs over the wall between
    two neighbouring doors (a door leaf is at most 1.3 m). A class with a usual width in
    ``MeasureConfig.clipped_width_m`` (doors) is first cut at the gaps below its top line and,
    when its mask reaches a side border of the image, from its far end in steps of that width
    (``usual_width_m`` of ``split_side_by_side``; docs/perception.md, "Instances")."""
    stack_gap_m: tuple[tuple[str, float], ...] = (("chair", 0.1), ("iv_pole", 1.0))
    """Segmentation network: ``[class, gap]`` pairs, metres. Pieces of the class one above the
    other with at most ``gap`` between them are joined (``instances.merge_stacked``): a
    chair's open back and its seat; an IV pole's bag and its base, the thin pole between
    them unsegmented."""
    floor_gap_m: tuple[tuple[str, float], ...] = (("chair", 0.6),)
    """``[class, gap]`` pairs of floor-standing classes, metres. An instance of the class whose
    lowest point is more than ``gap`` above the floor, with the wall or floor in plain view
    right below it, is not that object and is left out (``floor.floating_above_floor``; every
    segmenter, where the floor is known: keyframes of a robot base (``T_odom_base``), data
    sets with a ``[base]`` calibration): a red fire extinguisher on a wall taken for a red
    chair. Classes whose true objects often seem to float are not in it: a door whose lower
    part is out of view, an IV pole whose thin lower pole is missed."""
    max_top_m: tuple[tuple[str, float], ...] = tuple(
        (name, height) for name, _, height in CLASS_SIZE_M if name in _FLOOR_STANDING
    )
    """``[class, top]`` pairs of floor-standing classes: no object of the class reaches higher
    than ``top`` metres above the floor (the heights in ``types.CLASS_SIZE_M``). An instance of
    the class whose pixels lie on a surface that goes on, without a step in depth, above the
    mask to more than ``top`` + 0.3 m is a piece of a wall and is left out
    (``floor.part_of_taller_surface``; every segmenter, where the floor is known): a strip of
    corridor wall at the image border taken for a cabinet. Above a real cabinet the camera
    sees the wall behind it, a step further away. Doors are not in it: a door is flush with
    the wall above it."""
    min_top_m: tuple[tuple[str, float], ...] = tuple((name, 0.2) for name in _ON_FLOOR_BODY)
    """``[class, top]`` pairs of floor-standing classes: every object of the class reaches at
    least ``top`` metres above the floor (they stand 0.4 m tall or more). An instance of the
    class whose top lies lower is left out (``floor.flat_on_floor``; every segmenter, where the
    floor is known): the dark gap under a bed's footboard taken for a cart. IV poles are not in
    it (the network may find only a pole's base), nor doors and sinks (they do not stand on the
    floor)."""
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
