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

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Final, Protocol

import numpy as np
from numpy.typing import NDArray

from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.perception.instances import instances_from_classes
from wardmap.server.perception.masks import box_of_mask
from wardmap.server.perception.types import Instance
from wardmap.shared.detection import CocoMap, MaskConfig, decode_yolox, detection_labels, letterbox
from wardmap.shared.errors import ConfigError, GeometryError
from wardmap.shared.knowledge import BACKGROUND, KnowledgeGraph
from wardmap.shared.segmentation import INPUT_NAME, OUTPUT_NAME, Decoded, PlacementRule, SegContract

__all__ = [
    "DEFAULT_MODEL",
    "OnnxSegmenter",
    "Segmentation",
    "Segmenter",
    "YoloxDetector",
    "make_segmenter",
    "packaged_model_path",
]

log = logging.getLogger(__name__)

U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]


DEFAULT_MODEL: Final = "hospital_seg.onnx"
"""File name of the packaged segmentation network in ``wardmap.server/models``."""


@dataclass(frozen=True, eq=False)
class Segmentation:
    """What a segmenter found in one image.

    Attributes:
        class_map: uint8 (H, W) knowledge-graph class index per pixel (0 = background).
        confidence: float32 (H, W) score of each pixel's class in 0..1.
        instances: the instances, each with a mask in the image.
        inference_ms: wall time of pre-processing, network and post-processing.
        implausible: detections left out for a mask larger than any object of their class
            (``yolox:``; the size gate of :class:`~wardmap.shared.detection.MaskConfig`).
    """

    class_map: U8
    confidence: F32
    instances: list[Instance]
    inference_ms: float
    implausible: int = 0


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


class YoloxDetector:
    """A YOLOX-format COCO detector for real cameras (``wardmap.shared.detection``).

    Per image: letterbox -> network -> :func:`decode_yolox` -> COCO classes mapped to
    knowledge-graph classes (:class:`CocoMap`, ``shared/data/coco_to_kg.toml``) -> one mask
    per box by depth-based foreground segmentation, less the masks of smaller detections
    inside it, dropped when larger than any object of its class (:func:`detection_labels`;
    nearer instances win where masks overlap). An instance's confidence is its detection score.
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
        labels = detection_labels(
            detections,
            self._coco_map,
            self._kg,
            depth,
            min_score=self._score_threshold,
            config=self._mask_config,
        )
        class_map, instance_map = labels.class_image, labels.instance_image
        if labels.implausible:
            log.debug("YOLOX: %d detection(s) larger than any object of their class left out",
                      len(labels.implausible))
        # detection_labels numbers instances 1..K over the mapped detections at or above
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
        return Segmentation(class_map, confidence, instances, (time.perf_counter() - started) * 1e3,
                            len(labels.implausible))

    def __call__(self, bgr: U8, depth_m: F32 | None) -> list[Instance]:
        return self.segment(bgr, depth_m).instances


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
