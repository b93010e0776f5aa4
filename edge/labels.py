"""Label sources of the edge frontend: where per-pixel class labels come from.

The dynamic-point removal of paper 001 (Sec. 3.3-3.4, :mod:`wardmap.shared.semantic`)
needs a class image per frame. Sources are interchangeable behind the small
:class:`LabelSource` protocol and chosen by a spec string (config or command line)
through :func:`make_label_source`:

================  ==========================================================================
spec              source
================  ==========================================================================
``none``          no labels: every frame gives None (geometry-only tracking)
``oracle``        the simulator's ground truth: ``labels/`` instance ids + ``objects.json``
``onnx:PATH``     an ONNX model run with onnxruntime on the CPU, either a wardmap segmentation
                  network (``wardmap train-seg``, e.g. the packaged
                  ``server/models/hospital_seg.onnx``; recognised by its ``wardmap.classes``
                  metadata, :mod:`wardmap.shared.segmentation`) whose class map is the label
                  image, or a YOLOX-format detector whose boxes are turned into instance
                  masks with the depth image (:mod:`wardmap.shared.detection`)
================  ==========================================================================

:data:`LABEL_SOURCES` maps each spec prefix to its factory. Heavy imports (onnxruntime)
happen inside the factories, so importing this module loads nothing, and a missing
dependency or model file fails when the source is made, with a
:class:`~wardmap.shared.errors.ConfigError` saying what to do.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final, Protocol

import numpy as np
from numpy.typing import NDArray

from wardmap.shared.dataset import Frame, FrameSource
from wardmap.shared.detection import (
    CocoMap,
    Detections,
    MaskConfig,
    decode_yolox,
    labels_from_detections,
    letterbox,
)
from wardmap.shared.errors import ConfigError, DatasetError, KnowledgeGraphError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.segmentation import (
    INPUT_NAME,
    OUTPUT_NAME,
    PlacementRule,
    SegContract,
    is_segmentation_model,
)

__all__ = [
    "LABEL_SOURCES",
    "LabelResult",
    "LabelSource",
    "LabelSourceContext",
    "LabelSourceEntry",
    "NoLabels",
    "OnnxDetectorLabels",
    "OnnxSegmentationLabels",
    "OracleLabels",
    "make_label_source",
]

log = logging.getLogger(__name__)

U8 = NDArray[np.uint8]
U16 = NDArray[np.uint16]

WEIGHTS_HINT: Final = (
    "give either a wardmap segmentation network (the package ships one, trained by "
    "wardmap train-seg: wardmap/server/models/hospital_seg.onnx) or a YOLOX ONNX export "
    "(wardmap ships no detector weights; for example yolox_nano.onnx from the releases of "
    "github.com/Megvii-BaseDetection/YOLOX, see its demo/ONNXRuntime page) as onnx:PATH"
)
"""Which models fit and where to get them, appended to errors about a missing or bad model."""


@dataclass(frozen=True, eq=False)
class LabelResult:
    """Labels of one frame.

    Attributes:
        class_image: uint8 (H, W) knowledge-graph class index per rgb pixel
            (0 = background), the input of :func:`wardmap.shared.semantic.dynamic_mask`.
        instance_image: uint16 (H, W) instance id per pixel (0 = none), or None when the
            source has no instances.
        inference_ms: wall time this source spent producing the labels, in milliseconds
            (for a detector: pre-processing, network, decoding and masks).
    """

    class_image: U8
    instance_image: U16 | None
    inference_ms: float


class LabelSource(Protocol):
    """Anything that labels frames. ``labels`` returns None when it has no labels for the
    frame (the frontend then tracks that frame without semantic dynamic-point removal)."""

    name: str

    def labels(self, frame: Frame) -> LabelResult | None: ...


@dataclass(frozen=True)
class LabelSourceContext:
    """What a factory may use to build a source.

    Attributes:
        dataset: the data set being processed (the oracle reads its ground truth), or None
            for live sensors.
        kg: the knowledge graph whose class indices the class images use.
        threads: CPU threads a network may use (onnxruntime ``intra_op_num_threads``).
    """

    dataset: FrameSource | None
    kg: KnowledgeGraph
    threads: int = 1


LabelSourceFactory = Callable[[str, LabelSourceContext], LabelSource]
"""Builds a source from the text after ``prefix:`` (empty for bare specs) and the context."""


# ---------------------------------------------------------------------------- none


class NoLabels:
    """The ``none`` source: no labels for any frame."""

    def __init__(self) -> None:
        self.name = "none"

    def labels(self, frame: Frame) -> LabelResult | None:
        """Always None."""
        return None


# ---------------------------------------------------------------------------- oracle


class OracleLabels:
    """The ``oracle`` source: the simulator's ground-truth labels.

    A frame's ``labels`` image holds instance ids; ``objects.json`` gives each id's class
    (``objects[*].id`` / ``objects[*].class``). Pixels with ids not in ``objects.json``
    are background. Frames without a label image give None.
    """

    def __init__(self, dataset: FrameSource, kg: KnowledgeGraph) -> None:
        """Build the id -> class table.

        Raises:
            ConfigError: the data set has no ``labels/`` or no ``objects.json``, or an
                object's class is not in the knowledge graph.
            DatasetError: ``objects.json`` is malformed.
        """
        self.name = "oracle"
        root = dataset.root
        if not dataset.has_labels:
            raise ConfigError(f"label source 'oracle' needs ground-truth labels, but {root} has no "
                              "labels.txt / labels/ (only simulated data sets from `wardmap sim` have "
                              "them); use 'none' or 'onnx:PATH' for this data set")
        document = dataset.objects()
        if document is None:
            raise ConfigError(f"label source 'oracle' needs {root / 'objects.json'} to map instance ids "
                              "to classes, and it does not exist")
        if kg.num_classes > 256:
            raise ConfigError(f"knowledge graph has {kg.num_classes} classes; a uint8 class image holds 256")
        self._lut = _instance_class_lut(document, kg, root / "objects.json")

    def labels(self, frame: Frame) -> LabelResult | None:
        """Class image from the frame's instance ids, or None when the frame has no labels."""
        if frame.labels is None:
            return None
        started = time.perf_counter()
        instances = frame.labels
        class_image = np.take(self._lut, instances)
        elapsed_ms = (time.perf_counter() - started) * 1e3
        return LabelResult(class_image=class_image, instance_image=instances, inference_ms=elapsed_ms)


def _instance_class_lut(document: Mapping[str, Any], kg: KnowledgeGraph, where: Path) -> U8:
    """uint8 (65536,) table: instance id -> knowledge-graph class index (0 if unlisted)."""
    objects = document.get("objects")
    if not isinstance(objects, list):
        raise DatasetError(f"{where}: 'objects' must be a list of {{id, class, ...}} entries")
    lut = np.zeros(65536, dtype=np.uint8)
    for k, entry in enumerate(objects):
        if not isinstance(entry, Mapping):
            raise DatasetError(f"{where}: objects[{k}] must be an object, got {type(entry).__name__}")
        ident, name = entry.get("id"), entry.get("class")
        if isinstance(ident, bool) or not isinstance(ident, int) or not 0 < ident < 65536:
            raise DatasetError(f"{where}: objects[{k}].id must be an integer in 1..65535, got {ident!r}")
        if not isinstance(name, str):
            raise DatasetError(f"{where}: objects[{k}].class must be a string, got {name!r}")
        try:
            lut[ident] = kg.index_of(name)
        except KnowledgeGraphError as exc:
            raise ConfigError(f"{where}: objects[{k}] (id {ident}): {exc}") from exc
    return lut


# ---------------------------------------------------------------------------- onnx


class OnnxDetectorLabels:
    """The ``onnx:PATH`` source: a YOLOX-format detector on the CPU (onnxruntime).

    Each frame: rgb -> BGR letterbox -> network -> :func:`decode_yolox` -> COCO classes
    mapped to knowledge-graph classes (:class:`CocoMap`) -> instance masks from the depth
    image (:func:`labels_from_detections`).
    """

    def __init__(
        self,
        session: Any,
        kg: KnowledgeGraph,
        *,
        name: str,
        coco_map: CocoMap | None = None,
        score_threshold: float = 0.3,
        nms_iou: float = 0.45,
        mask_config: MaskConfig | None = None,
    ) -> None:
        """Wrap an ``onnxruntime.InferenceSession`` (built by the ``onnx`` factory).

        Raises:
            ConfigError: the model's input or output does not have the YOLOX layout, or
                the class map does not fit the model or the knowledge graph.
        """
        self.name = name
        self._session = session
        self._kg = kg
        self._coco_map = coco_map or CocoMap.load()
        self._coco_map.kg_lut(kg)  # fail now, not on the first frame, if a mapped class is unknown
        self._score_threshold = score_threshold
        self._nms_iou = nms_iou
        self._mask_config = mask_config or MaskConfig()
        inputs, outputs = session.get_inputs(), session.get_outputs()
        if len(inputs) != 1 or len(outputs) < 1:
            raise ConfigError(f"{name}: expected one input and an output, got {len(inputs)} inputs and "
                              f"{len(outputs)} outputs; {WEIGHTS_HINT}")
        self._input_name = inputs[0].name
        in_shape, out_shape = list(inputs[0].shape), list(outputs[0].shape)
        size = in_shape[2] if len(in_shape) == 4 else None
        if len(in_shape) != 4 or in_shape[1] != 3 or in_shape[2] != in_shape[3] or not isinstance(size, int):
            raise ConfigError(f"{name}: input {self._input_name!r} has shape {in_shape}, expected a YOLOX "
                              f"input [1, 3, S, S]; {WEIGHTS_HINT}")
        self._input_size = size
        classes = len(self._coco_map.names)
        if len(out_shape) != 3 or (isinstance(out_shape[2], int) and out_shape[2] != 5 + classes):
            raise ConfigError(f"{name}: output has shape {out_shape}, expected a YOLOX output "
                              f"[1, A, {5 + classes}] for the {classes} classes of "
                              f"{self._coco_map.source}; {WEIGHTS_HINT}")

    @property
    def input_size(self) -> int:
        """Network input side length in pixels."""
        return self._input_size

    def detect(self, rgb: U8) -> Detections:
        """Detections in a uint8 (H, W, 3) RGB image, in its pixel coordinates."""
        bgr = np.ascontiguousarray(rgb[..., ::-1])
        blob, ratio = letterbox(bgr, self._input_size)
        output = self._session.run(None, {self._input_name: blob})[0]
        return decode_yolox(output, ratio, (bgr.shape[1], bgr.shape[0]),
                            score_threshold=self._score_threshold, nms_iou=self._nms_iou)

    def labels(self, frame: Frame) -> LabelResult:
        """Detect, map classes and mask instances with the frame's depth."""
        started = time.perf_counter()
        detections = self.detect(frame.rgb)
        class_image, instance_image = labels_from_detections(
            detections, self._coco_map, self._kg, frame.depth_m,
            min_score=self._score_threshold, config=self._mask_config,
        )
        elapsed_ms = (time.perf_counter() - started) * 1e3
        return LabelResult(class_image=class_image, instance_image=instance_image, inference_ms=elapsed_ms)


class OnnxSegmentationLabels:
    """The ``onnx:PATH`` source with a wardmap segmentation network (:mod:`wardmap.shared.segmentation`).

    Each frame: rgb -> the network's input size -> per-pixel argmax, with the knowledge
    graph's placement check, resized back (class boundaries from the bilinearly upsampled
    logits; ``SegContract.decode``). The network's class indices are the knowledge
    graph's (checked at start-up), so its class map is the label image; it has no instances.
    """

    def __init__(self, session: Any, kg: KnowledgeGraph, *, name: str) -> None:
        """Wrap an ``onnxruntime.InferenceSession`` of a segmentation network.

        Raises:
            ConfigError: the model breaks the contract (names, shapes, metadata, classes).
        """
        self.name = name
        self._session = session
        meta = dict(session.get_modelmeta().custom_metadata_map)
        self._contract = SegContract.check(
            meta,
            [(i.name, i.shape) for i in session.get_inputs()],
            [(o.name, o.shape) for o in session.get_outputs()],
            kg,
            name,
        )
        self._placement = PlacementRule.from_knowledge(kg, self._contract.class_names)

    def labels(self, frame: Frame) -> LabelResult:
        started = time.perf_counter()
        bgr = np.ascontiguousarray(frame.rgb[..., ::-1])
        x = self._contract.preprocess(bgr, frame.depth_m)  # an RGB-D network also takes the depth
        (logits,) = self._session.run([OUTPUT_NAME], {INPUT_NAME: x})
        classes = self._contract.decode(logits, bgr.shape[:2], self.name, placement=self._placement).classes
        elapsed_ms = (time.perf_counter() - started) * 1e3
        return LabelResult(class_image=classes, instance_image=None, inference_ms=elapsed_ms)


# ---------------------------------------------------------------------------- registry


def _make_none(argument: str, context: LabelSourceContext) -> LabelSource:
    return NoLabels()


def _make_oracle(argument: str, context: LabelSourceContext) -> LabelSource:
    if context.dataset is None:
        raise ConfigError("label source 'oracle' reads the simulator's ground truth and needs a data set; "
                          "live sensors have none (use 'none' or 'onnx:PATH')")
    return OracleLabels(context.dataset, context.kg)


def _make_onnx(argument: str, context: LabelSourceContext) -> LabelSource:
    path = Path(argument).expanduser()
    if not path.is_file():
        raise ConfigError(f"label source 'onnx:{argument}': model file not found: {path}; {WEIGHTS_HINT}")
    try:
        import onnxruntime as ort
    except ImportError as exc:
        raise ConfigError("label source 'onnx' needs the onnxruntime package "
                          f"(pip install onnxruntime): {exc}") from exc
    options = ort.SessionOptions()
    options.intra_op_num_threads = context.threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.log_severity_level = 3  # errors only: onnxruntime logs to stderr on its own
    try:
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own untyped errors for unreadable models
        raise ConfigError(f"label source 'onnx:{argument}': cannot load {path} as an ONNX model: "
                          f"{exc}; {WEIGHTS_HINT}") from exc
    log.info("onnx label source: %s on %d CPU thread(s)", path, context.threads)
    if is_segmentation_model(dict(session.get_modelmeta().custom_metadata_map)):
        return OnnxSegmentationLabels(session, context.kg, name=f"onnx:{path.name}")
    return OnnxDetectorLabels(session, context.kg, name=f"onnx:{path.name}")


@dataclass(frozen=True)
class LabelSourceEntry:
    """One registry entry.

    Attributes:
        factory: builds the source from the argument text and the context.
        argument: placeholder of the argument after ``prefix:`` (e.g. ``"PATH"``), or
            None when the spec takes no argument.
    """

    factory: LabelSourceFactory
    argument: str | None = None

    def usage(self, prefix: str) -> str:
        return prefix if self.argument is None else f"{prefix}:{self.argument}"


LABEL_SOURCES: Final[Mapping[str, LabelSourceEntry]] = MappingProxyType({
    "none": LabelSourceEntry(_make_none),
    "oracle": LabelSourceEntry(_make_oracle),
    "onnx": LabelSourceEntry(_make_onnx, "PATH"),
})
"""Spec prefix -> factory; a new kind of source is one more entry here."""


def _usage() -> str:
    return ", ".join(entry.usage(prefix) for prefix, entry in LABEL_SOURCES.items())


def make_label_source(
    spec: str,
    *,
    dataset: FrameSource | None,
    kg: KnowledgeGraph,
    threads: int = 1,
) -> LabelSource:
    """Build the label source named by ``spec`` (``none``, ``oracle`` or ``onnx:PATH``).

    Args:
        spec: ``prefix`` or ``prefix:argument``; the prefix picks a factory from
            :data:`LABEL_SOURCES`.
        dataset: the data set being processed, or None for live sensors.
        kg: the knowledge graph for class indices.
        threads: CPU threads for network inference (at least 1).

    Raises:
        ConfigError: unknown prefix (the message lists the known ones), a missing or
            unexpected argument, a bad thread count, or a source that cannot be built
            (missing model file or dependency, data set without ground truth).
    """
    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError(f"label source spec must be a non-empty string ({_usage()}), got {spec!r}")
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ConfigError(f"label source threads must be a positive integer, got {threads!r}")
    prefix, colon, argument = spec.strip().partition(":")
    entry = LABEL_SOURCES.get(prefix)
    if entry is None:
        raise ConfigError(f"unknown label source {spec!r}; known: {_usage()}")
    if entry.argument is not None and not argument:
        raise ConfigError(f"label source {prefix!r} needs an argument: {entry.usage(prefix)}")
    if entry.argument is None and colon:
        raise ConfigError(f"label source {prefix!r} takes no argument, got {spec!r}")
    return entry.factory(argument, LabelSourceContext(dataset=dataset, kg=kg, threads=threads))
