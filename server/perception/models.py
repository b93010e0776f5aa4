"""Segmenters of the server: the trained hospital network and a YOLOX detector adapter.

Both sit behind the :class:`Segmenter` protocol and are chosen by a spec string
(:func:`make_segmenter`, ``[perception] segmenter`` in ``deploy/perception.toml``):

=================  ========================================================================
spec               segmenter
=================  ========================================================================
``model``          the packaged network ``wardmap/server/models/hospital_seg.onnx``
``model:PATH``     a segmentation network in the ONNX contract below (:class:`OnnxSegmenter`)
``yolox:PATH``     a YOLOX-format COCO detector + depth masks for real cameras
                   (:class:`YoloxDetector`, ``wardmap.shared.detection``)
``PATH``           any other text is a path: the same as ``model:PATH``
=================  ========================================================================

ONNX contract of a segmentation network (what ``wardmap train-seg`` exports; checked and
pre/post-processed by :mod:`wardmap.shared.segmentation`, which the edge's label source shares):

- one input ``image``: float32 ``[1, 3, H, W]``, RGB, values 0..1 (any normalisation is
  inside the model), or ``[1, 4, H, W]``: RGB and depth in metres (an RGB-D network, which
  then needs the frame's depth);
- one output ``logits``: float32 ``[1, C, H, W]``, C = 1 + the knowledge graph's classes
  (index 0 background, index i = the i-th ``[[classes]]`` of
  ``shared/data/knowledge_graph.toml``);
- metadata ``wardmap.classes``: JSON list of the C class names in index order (first
  ``"background"``), and ``wardmap.input_size``: ``"WxH"`` (e.g. ``"320x240"``).

Everything is checked when the segmenter is made; a missing, unreadable or mismatching
model raises :class:`~wardmap.shared.errors.ConfigError` naming the file. onnxruntime is
imported inside the constructors, so importing this module loads nothing.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Final, NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray

from wardmap.server.perception.instances import (
    box_of_mask,
    flat_on_floor,
    floating_above_floor,
    instances_from_classes,
    merge_stacked,
    part_of_taller_surface,
    split_side_by_side,
)
from wardmap.server.perception.measure import MeasureConfig
from wardmap.server.perception.types import CLASS_SIZE_M, Instance
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.config import load_config
from wardmap.shared.detection import CocoMap, MaskConfig, decode_yolox, labels_from_detections, letterbox
from wardmap.shared.errors import ConfigError, GeometryError
from wardmap.shared.knowledge import BACKGROUND, KnowledgeGraph
from wardmap.shared.segmentation import INPUT_NAME, OUTPUT_NAME, Decoded, PlacementRule, SegContract

__all__ = [
    "DEFAULT_MODEL",
    "LeftOut",
    "OnnxSegmenter",
    "PerceptionConfig",
    "Segmentation",
    "Segmenter",
    "YoloxDetector",
    "drop_floating",
    "drop_floor_pieces",
    "drop_misplaced",
    "drop_wall_pieces",
    "floor_under",
    "load_perception_config",
    "make_segmenter",
    "measure_config_for",
    "packaged_model_path",
    "split_instances",
]

log = logging.getLogger(__name__)

U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]

DEFAULT_MODEL: Final = "hospital_seg.onnx"
"""File name of the packaged segmentation network in ``wardmap.server/models``."""

_FLOOR_STANDING = ("bed", "cabinet", "desk", "cart", "wheelchair", "chair", "iv_pole")
"""Classes that stand on the floor, so their top height above it is bounded
(``PerceptionConfig.max_top_m``)."""
_ON_FLOOR_BODY = tuple(name for name in _FLOOR_STANDING if name != "iv_pole")
"""Floor-standing classes whose body rises from the floor, so their top is bounded from below
too (``PerceptionConfig.min_top_m``); not IV poles, of which the network may find only the base."""


# ---------------------------------------------------------------------------- config


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


def measure_config_for(config: PerceptionConfig, spec: str) -> MeasureConfig:
    """The measurement parameters for segmenter ``spec``: ``config.measure``, with
    ``detector_cluster_gap_m`` as the cluster gap for a ``yolox:`` detector when none is set."""
    m = config.measure
    if spec.strip().startswith("yolox:") and m.cluster_gap_m == 0 and config.detector_cluster_gap_m > 0:
        return dataclasses.replace(m, cluster_gap_m=config.detector_cluster_gap_m)
    return m


def split_instances(instances: Sequence[Instance], depth_m: NDArray[np.float32], camera: PinholeCamera,
                    config: PerceptionConfig, spec: str) -> list[Instance]:
    """The segmentation network's (``model`` specs) instances of the ``split_width_m`` classes cut
    into side-by-side objects (:func:`~wardmap.server.perception.instances.split_side_by_side`),
    then pieces of the ``stack_gap_m`` classes one above the other joined
    (:func:`~wardmap.server.perception.instances.merge_stacked`: a chair's open back and its
    seat); other segmenters' instances are returned unchanged (a detector boxes each chair)."""
    out = list(instances)
    if not spec.strip().startswith("model"):
        return out
    usual = dict(config.measure.clipped_width_m)
    for name, width in config.split_width_m:
        out = split_side_by_side(out, depth_m, camera, classes=(name,), width_m=width,
                                 min_pixels=config.min_pixels, usual_width_m=usual.get(name))
    for name, gap in config.stack_gap_m:
        out = merge_stacked(out, depth_m, camera, classes=(name,), max_gap_m=gap)
    return out


def floor_under(T_world_camera: NDArray[np.float64], T_base_camera: NDArray[np.float64]) -> float:
    """Height (metres, world z) of the floor under a camera on a robot base whose frame sits on
    the floor (``T_base_camera``: the camera in the base frame): the ``floor_z_m`` of
    :func:`drop_floating`."""
    return float((np.asarray(T_world_camera) @ np.linalg.inv(T_base_camera))[2, 3])


def drop_floating(instances: Sequence[Instance], depth_m: NDArray[np.float32], camera: PinholeCamera,
                  config: PerceptionConfig, T_world_camera: NDArray[np.float64],
                  floor_z_m: float | None) -> tuple[list[Instance], int]:
    """``instances`` without those of the ``floor_gap_m`` classes that float above the floor
    (:func:`~wardmap.server.perception.instances.floating_above_floor`), and how many were
    left out. ``floor_z_m``: the floor's height in the frame of ``T_world_camera`` (world z
    up), metres; None (floor unknown: a hand-held camera) keeps every instance."""
    return _drop(instances, floor_z_m, config.floor_gap_m, lambda floor, table: floating_above_floor(
        instances, depth_m, camera, T_world_camera, floor_z_m=floor, max_gap_m=table))


def drop_wall_pieces(instances: Sequence[Instance], depth_m: NDArray[np.float32], camera: PinholeCamera,
                     config: PerceptionConfig, T_world_camera: NDArray[np.float64],
                     floor_z_m: float | None) -> tuple[list[Instance], int]:
    """``instances`` without those of the ``max_top_m`` classes that are a piece of a taller
    surface (:func:`~wardmap.server.perception.instances.part_of_taller_surface`), and how
    many were left out. ``floor_z_m`` as for :func:`drop_floating`; None keeps every instance."""
    return _drop(instances, floor_z_m, config.max_top_m, lambda floor, table: part_of_taller_surface(
        instances, depth_m, camera, T_world_camera, floor_z_m=floor, max_top_m=table))


def drop_floor_pieces(instances: Sequence[Instance], depth_m: NDArray[np.float32], camera: PinholeCamera,
                      config: PerceptionConfig, T_world_camera: NDArray[np.float64],
                      floor_z_m: float | None) -> tuple[list[Instance], int]:
    """``instances`` without those of the ``min_top_m`` classes that lie flat on the floor
    (:func:`~wardmap.server.perception.instances.flat_on_floor`), and how many were left out.
    ``floor_z_m`` as for :func:`drop_floating`; None keeps every instance."""
    return _drop(instances, floor_z_m, config.min_top_m, lambda floor, table: flat_on_floor(
        instances, depth_m, camera, T_world_camera, floor_z_m=floor, min_top_m=table))


def _drop(instances: Sequence[Instance], floor_z_m: float | None, pairs: Sequence[tuple[str, float]],
          flags: Callable[[float, dict[str, float]], list[bool]]) -> tuple[list[Instance], int]:
    """The instances ``flags`` (called with the floor height and the ``[class, value]`` ``pairs``
    as a dict) does not flag, and how many it flagged; every instance when the floor is unknown
    or ``pairs`` is empty."""
    if floor_z_m is None or not pairs or not instances:
        return list(instances), 0
    return _without(instances, flags(floor_z_m, dict(pairs)))


class LeftOut(NamedTuple):
    """How many instances :func:`drop_misplaced` left out, by check."""

    floating: int
    """Floating above the floor (``floor_gap_m``)."""
    walls: int
    """A piece of a surface taller than any object of the class (``max_top_m``)."""
    floors: int
    """Flat on the floor, lower than any object of the class (``min_top_m``)."""


def drop_misplaced(instances: Sequence[Instance], depth_m: NDArray[np.float32], camera: PinholeCamera,
                   config: PerceptionConfig, T_world_camera: NDArray[np.float64],
                   floor_z_m: float | None) -> tuple[list[Instance], LeftOut]:
    """``instances`` after the three floor checks (:func:`drop_floating`,
    :func:`drop_wall_pieces`, :func:`drop_floor_pieces`, in that order), and how many each left
    out. ``floor_z_m`` as for :func:`drop_floating`; None keeps every instance."""
    kept, floating = drop_floating(instances, depth_m, camera, config, T_world_camera, floor_z_m)
    kept, walls = drop_wall_pieces(kept, depth_m, camera, config, T_world_camera, floor_z_m)
    kept, floors = drop_floor_pieces(kept, depth_m, camera, config, T_world_camera, floor_z_m)
    return kept, LeftOut(floating, walls, floors)


def _without(instances: Sequence[Instance], flags: Sequence[bool]) -> tuple[list[Instance], int]:
    """The instances whose flag is False, and how many were flagged."""
    kept = [inst for inst, flagged in zip(instances, flags, strict=True) if not flagged]
    return kept, len(instances) - len(kept)


def load_perception_config(path: str | Path | None) -> PerceptionConfig:
    """The ``[perception]`` table of a TOML file (defaults when ``path`` is None).

    Raises:
        ConfigError: missing file, malformed TOML, unknown key or bad value (named).
    """
    return load_config(PerceptionConfig, path, section="perception")


# ---------------------------------------------------------------------------- protocol


@dataclass(frozen=True, eq=False)
class Segmentation:
    """What a segmenter found in one image.

    Attributes:
        class_map: uint8 (H, W) knowledge-graph class index per pixel (0 = background).
        confidence: float32 (H, W) score of each pixel's class in 0..1.
        instances: the instances, each with a mask in the image.
        inference_ms: wall time of pre-processing, network and post-processing.
    """

    class_map: U8
    confidence: F32
    instances: list[Instance]
    inference_ms: float


class Segmenter(Protocol):
    """Anything that finds knowledge-graph instances in a colour + depth image."""

    @property
    def class_names(self) -> tuple[str, ...]:
        """Class index -> name; index 0 is ``"background"``, then the knowledge graph's classes."""
        ...

    def segment(self, bgr: U8, depth_m: F32 | None) -> Segmentation:
        """Classes and instances of a uint8 (H, W, 3) BGR image with float32 (H, W) depth in metres."""
        ...

    def __call__(self, bgr: U8, depth_m: F32 | None) -> list[Instance]:
        """The instances of :meth:`segment`."""
        ...


def _check_bgr(bgr: Any) -> U8:
    image = np.asarray(bgr)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3 or 0 in image.shape:
        raise GeometryError(f"segment: expected a uint8 (H, W, 3) BGR image, got {image.dtype} {image.shape}")
    return image


def _check_depth(depth_m: Any, shape: tuple[int, int]) -> F32:
    """Depth as float32 (H, W); zeros (no data) when None."""
    if depth_m is None:
        return np.zeros(shape, np.float32)
    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.shape != shape:
        raise GeometryError(f"segment: depth {depth.shape} does not match the image {shape}")
    return depth


def _session(path: Path, threads: int, what: str) -> Any:
    """An onnxruntime CPU session of ``path``; ConfigError naming the file if it cannot be made."""
    if not path.is_file():
        raise ConfigError(f"{what}: model file not found: {path}")
    try:
        import onnxruntime as ort
    except ImportError as exc:  # a dependency of wardmap; only a broken install lacks it
        raise ConfigError(f"{what} needs the onnxruntime package (pip install onnxruntime): {exc}") from exc
    if threads < 1:
        raise ConfigError(f"{what}: threads must be >= 1, got {threads}")
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.log_severity_level = 3  # errors only: onnxruntime logs to stderr on its own
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own untyped errors for unreadable models
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ConfigError(f"{what}: {path} is not a readable ONNX model: {first}") from exc


# ---------------------------------------------------------------------------- trained network


class OnnxSegmenter:
    """A segmentation network in the wardmap ONNX contract (module docstring), on the CPU.

    Per image: BGR -> RGB, resized to the model's input size, 0..1 -> network (and its
    mirror image, ``flip_average``) -> unsure regions vetoed (``min_region_confidence``) ->
    the knowledge graph's placement check (``placement_check``) -> per-pixel argmax of the
    logits and softmax maximum as confidence -> both resized back to the image (nearest;
    class boundaries from the bilinearly upsampled logits, ``refine_edges``) ->
    :func:`instances_from_classes` (per-class connected components split at depth jumps).
    """

    def __init__(
        self,
        path: str | Path,
        threads: int = 1,
        *,
        kg: KnowledgeGraph | None = None,
        min_pixels: int = PerceptionConfig.min_pixels,
        depth_jump_m: float = PerceptionConfig.depth_jump_m,
        depth_jump_relative: float = PerceptionConfig.depth_jump_relative,
        min_confidence: float = PerceptionConfig.min_confidence,
        trim_classes: Sequence[str] = PerceptionConfig.trim_classes,
        flip_average: bool = PerceptionConfig.flip_average,
        refine_edges: bool = PerceptionConfig.refine_edges,
        placement_check: bool = PerceptionConfig.placement_check,
        min_region_confidence: float = PerceptionConfig.min_region_confidence,
    ) -> None:
        """Open and check the model.

        ``flip_average``: average the logits of the image and of its mirror image
        (:attr:`PerceptionConfig.flip_average`); ``refine_edges``, ``placement_check`` and
        ``min_region_confidence``: the :class:`PerceptionConfig` attributes of those names.

        Raises:
            ConfigError: missing file, not ONNX, wrong input/output names or shapes,
                missing or malformed metadata, or classes that differ from the knowledge
                graph's (each message names the file).
        """
        self.path = Path(path).expanduser()
        what = f"segmentation model {self.path}"
        self._what = what
        self._session = _session(self.path, threads, "segmentation model")
        kg = kg or KnowledgeGraph.load()
        meta = dict(self._session.get_modelmeta().custom_metadata_map)
        self._contract = SegContract.check(
            meta,
            [(i.name, i.shape) for i in self._session.get_inputs()],
            [(o.name, o.shape) for o in self._session.get_outputs()],
            kg,
            what,
        )
        self._class_names = self._contract.class_names
        self._input_wh = self._contract.input_wh
        self._min_pixels = min_pixels
        self._depth_jump_m = depth_jump_m
        self._depth_jump_relative = depth_jump_relative
        self._min_confidence = min_confidence
        unknown = sorted(set(trim_classes) - set(self._class_names[1:]))
        if unknown:
            raise ConfigError(f"{what}: trim_classes names classes the model does not have: {unknown}")
        self._trim_classes = tuple(self._class_names.index(c) for c in trim_classes)
        self._flip_average = bool(flip_average)
        self._refine_edges = bool(refine_edges)
        self._placement = PlacementRule.from_knowledge(kg, self._class_names) if placement_check else None
        if not 0.0 <= min_region_confidence <= 1.0:
            raise ConfigError(f"{what}: min_region_confidence must lie in 0..1, got {min_region_confidence}")
        self._min_region_confidence = float(min_region_confidence)
        w, h = self._input_wh
        log.info("segmentation model %s: %d classes, input %dx%d %s, %d thread(s)%s",
                 self.path, len(self._class_names), w, h, "RGB-D" if self.depth_input else "RGB", threads,
                 ", flip-averaged" if self._flip_average else "")

    @property
    def class_names(self) -> tuple[str, ...]:
        return self._class_names

    @property
    def input_size(self) -> tuple[int, int]:
        """``(width, height)`` the network runs at."""
        return self._input_wh

    @property
    def depth_input(self) -> bool:
        """True for an RGB-D network: :meth:`classify` needs the depth image."""
        return self._contract.depth_input

    def classify(self, bgr: U8, depth_m: F32 | None = None) -> tuple[U8, F32]:
        """Per-pixel classes uint8 (H, W) and softmax confidence float32 (H, W) of a BGR image
        (and its (H, W) depth in metres, which an RGB-D network needs). With ``flip_average``
        the logits are the mean of the image's and of its mirror image's (mirrored back).

        Raises:
            GeometryError: a malformed image or depth; no depth for an RGB-D network.
        """
        out = self._decode(bgr, depth_m)
        return out.classes, out.confidence

    def _decode(self, bgr: U8, depth_m: F32 | None) -> Decoded:
        image = _check_bgr(bgr)
        x = self._contract.preprocess(image, depth_m)  # refuses an RGB-D network without depth
        (logits,) = self._session.run([OUTPUT_NAME], {INPUT_NAME: x})
        if self._flip_average:
            (mirrored,) = self._session.run([OUTPUT_NAME], {INPUT_NAME: np.ascontiguousarray(x[..., ::-1])})
            back = np.asarray(mirrored, np.float32)[..., ::-1]
            logits = (np.asarray(logits, np.float32) + back) * np.float32(0.5)
        return self._contract.decode(logits, image.shape[:2], self._what, placement=self._placement,
                                     refine_edges=self._refine_edges,
                                     min_region_confidence=self._min_region_confidence)

    def segment(self, bgr: U8, depth_m: F32 | None) -> Segmentation:
        started = time.perf_counter()
        out = self._decode(bgr, depth_m)
        classes, confidence = out.classes, out.confidence
        depth = _check_depth(depth_m, classes.shape)
        # Instances from the nearest cells' classes: the refined boundary pixels straddle depth
        # edges, and with them the association's object counts fell (docs/perception.md).
        instances = instances_from_classes(
            out.nearest,
            depth,
            self._class_names,
            confidence,
            depth_jump_m=self._depth_jump_m,
            depth_jump_relative=self._depth_jump_relative,
            min_pixels=self._min_pixels,
            min_confidence=self._min_confidence,
            trim_classes=self._trim_classes,
        )
        return Segmentation(classes, confidence, instances, (time.perf_counter() - started) * 1e3)

    def __call__(self, bgr: U8, depth_m: F32 | None) -> list[Instance]:
        return self.segment(bgr, depth_m).instances


# ---------------------------------------------------------------------------- YOLOX adapter


class YoloxDetector:
    """A YOLOX-format COCO detector for real cameras (``wardmap.shared.detection``).

    Per image: letterbox -> network -> :func:`decode_yolox` -> COCO classes mapped to
    knowledge-graph classes (:class:`CocoMap`, ``shared/data/coco_to_kg.toml``) -> one mask
    per box by depth-based foreground segmentation (:func:`labels_from_detections`, nearer
    instances win where masks overlap). An instance's confidence is its detection score.
    """

    def __init__(
        self,
        path: str | Path,
        threads: int = 1,
        *,
        coco_map: CocoMap | None = None,
        kg: KnowledgeGraph | None = None,
        score_threshold: float = PerceptionConfig.score_threshold,
        nms_iou: float = PerceptionConfig.nms_iou,
        mask_config: MaskConfig | None = None,
        min_pixels: int = PerceptionConfig.min_pixels,
    ) -> None:
        """Open and check the detector.

        Raises:
            ConfigError: missing or unreadable file, an input that is not ``[1, 3, S, S]``,
                or an output that is not ``[1, A, 5 + classes of the COCO map]``.
        """
        self.path = Path(path).expanduser()
        what = f"YOLOX detector {self.path}"
        self._session = _session(self.path, threads, "YOLOX detector")
        self._kg = kg or KnowledgeGraph.load()
        self._coco_map = coco_map or CocoMap.load()
        self._coco_map.kg_lut(self._kg)  # an unknown mapped class fails now, not on the first image
        self._class_names = (BACKGROUND, *self._kg.names)
        self._score_threshold = score_threshold
        self._nms_iou = nms_iou
        self._mask_config = mask_config or MaskConfig()
        self._min_pixels = min_pixels
        inputs, outputs = self._session.get_inputs(), self._session.get_outputs()
        if len(inputs) != 1 or len(outputs) < 1:
            raise ConfigError(
                f"{what}: expected one input and an output, got {len(inputs)} input(s) and "
                f"{len(outputs)} output(s)"
            )
        self._input_name = inputs[0].name
        in_shape, out_shape = list(inputs[0].shape), list(outputs[0].shape)
        side = in_shape[2] if len(in_shape) == 4 else None
        if len(in_shape) != 4 or in_shape[1] != 3 or in_shape[2] != in_shape[3] or not isinstance(side, int):
            raise ConfigError(
                f"{what}: input {self._input_name!r} has shape {in_shape}, expected a YOLOX "
                f"input [1, 3, S, S]"
            )
        self._input_size = side
        n = len(self._coco_map.names)
        if len(out_shape) != 3 or (isinstance(out_shape[2], int) and out_shape[2] != 5 + n):
            raise ConfigError(
                f"{what}: output has shape {out_shape}, expected a YOLOX output "
                f"[1, A, {5 + n}] for the {n} classes of {self._coco_map.source}"
            )
        log.info("YOLOX detector %s: input %d, %d thread(s)", self.path, side, threads)

    @property
    def class_names(self) -> tuple[str, ...]:
        return self._class_names

    def segment(self, bgr: U8, depth_m: F32 | None) -> Segmentation:
        started = time.perf_counter()
        image = _check_bgr(bgr)
        height, width = image.shape[:2]
        depth = None if depth_m is None else _check_depth(depth_m, (height, width))
        blob, ratio = letterbox(image, self._input_size)
        output = self._session.run(None, {self._input_name: blob})[0]
        detections = decode_yolox(
            output, ratio, (width, height), score_threshold=self._score_threshold, nms_iou=self._nms_iou
        )
        class_map, instance_map = labels_from_detections(
            detections,
            self._coco_map,
            self._kg,
            depth,
            min_score=self._score_threshold,
            config=self._mask_config,
        )
        # labels_from_detections numbers instances 1..K over the mapped detections at or above
        # min_score, highest score first (detections are already sorted by score).
        lut = self._coco_map.kg_lut(self._kg)
        cls = detections.coco_class
        mapped = np.where((cls >= 0) & (cls < lut.shape[0]), lut[np.clip(cls, 0, lut.shape[0] - 1)], -1)
        used = np.flatnonzero((mapped > 0) & (detections.scores >= self._score_threshold))
        used = used[np.argsort(-detections.scores[used], kind="stable")]
        confidence = np.zeros((height, width), np.float32)
        instances: list[Instance] = []
        ids, counts = np.unique(instance_map, return_counts=True)
        for instance_id, count in zip(ids.tolist(), counts.tolist(), strict=True):
            if instance_id == 0:
                continue
            k = int(used[instance_id - 1])
            score = float(detections.scores[k])
            mask = instance_map == instance_id
            confidence[mask] = score
            if count < self._min_pixels:
                continue
            name = self._class_names[int(mapped[k])]
            instances.append(Instance(name, score, mask, box_of_mask(mask)))
        instances.sort(key=lambda inst: -inst.confidence)
        return Segmentation(class_map, confidence, instances, (time.perf_counter() - started) * 1e3)

    def __call__(self, bgr: U8, depth_m: F32 | None) -> list[Instance]:
        return self.segment(bgr, depth_m).instances


# ---------------------------------------------------------------------------- factory


def packaged_model_path() -> Path:
    """Path of the packaged ``hospital_seg.onnx`` (it may not exist yet)."""
    return Path(str(resources.files("wardmap.server").joinpath("models", DEFAULT_MODEL)))


def make_segmenter(
    spec: str,
    config: PerceptionConfig | None = None,
    *,
    threads: int | None = None,
    kg: KnowledgeGraph | None = None,
) -> Segmenter:
    """Build the segmenter named by ``spec`` (module docstring table).

    Args:
        spec: ``model``, ``model:PATH``, ``yolox:PATH`` or a bare path (= ``model:PATH``).
        config: instance and YOLOX parameters (defaults when None); ``config.segmenter`` is
            not read, ``spec`` is.
        threads: CPU threads, overriding ``config.threads``.
        kg: the knowledge graph (the packaged one when None).

    Raises:
        ConfigError: an empty spec, the packaged model not installed, or any model problem.
    """
    cfg = config or PerceptionConfig()
    n = cfg.threads if threads is None else threads
    text = spec.strip()
    if not text:
        raise ConfigError("segmenter spec is empty; use 'model', 'model:PATH' or 'yolox:PATH'")
    if text.startswith("yolox:"):
        return YoloxDetector(
            text[len("yolox:") :],
            n,
            kg=kg,
            score_threshold=cfg.score_threshold,
            nms_iou=cfg.nms_iou,
            mask_config=cfg.masks,
            min_pixels=cfg.min_pixels,
        )
    if text == "model":
        path = packaged_model_path()
        if not path.is_file():
            raise ConfigError(
                f"the packaged segmentation model is not installed ({path}); train one with "
                "'wardmap train-seg --out MODEL.onnx' and pass model:MODEL.onnx"
            )
    elif text.startswith("model:"):
        path = Path(text[len("model:") :])
    else:
        path = Path(text)
    return OnnxSegmenter(
        path,
        n,
        kg=kg,
        min_pixels=cfg.min_pixels,
        depth_jump_m=cfg.depth_jump_m,
        depth_jump_relative=cfg.depth_jump_relative,
        min_confidence=cfg.min_confidence,
        trim_classes=cfg.trim_classes,
        flip_average=cfg.flip_average,
        refine_edges=cfg.refine_edges,
        placement_check=cfg.placement_check,
        min_region_confidence=cfg.min_region_confidence,
    )
