"""Decoding of YOLOX-format detectors and detection-based label images.

Pure array code (numpy, cv2) shared by every runtime that executes a detector; the
runtime itself (onnxruntime) lives at the edges (``wardmap.edge.labels``).

The YOLOX ONNX format (the export of Megvii's YOLOX, e.g. YOLOX-Nano):

- input: float32 ``[1, 3, S, S]`` (S = 416 for the Nano/Tiny exports), BGR channel
  order, values 0..255 without normalisation, the image resized keeping its aspect
  ratio by ``ratio = min(S / H, S / W)`` and padded with 114 at the right and bottom
  (:func:`letterbox`);
- output: float32 ``[1, A, 5 + C]`` raw grid outputs for strides 8, 16 and 32, cells in
  row-major order per stride (A = 3549 for S = 416); per row ``(x, y, w, h, objectness,
  C class scores)`` with objectness and class scores already passed through a sigmoid.
  Decoding (:func:`decode_yolox`): ``xy = (out_xy + grid_xy) * stride``,
  ``wh = exp(out_wh) * stride`` (box centre and size in letterboxed pixels),
  ``score = objectness * class_score`` for the best class, per-class non-maximum
  suppression, and division by ``ratio`` back to original pixels.

Detections become label images for the semantic descriptor (paper 001 Sec. 3.3) with
:func:`labels_from_detections`: COCO classes are mapped to knowledge-graph classes by the
data file ``shared/data/coco_to_kg.toml`` (:class:`CocoMap`), and each box becomes an
instance mask by depth-based foreground segmentation, less the masks of smaller detections
inside it, dropped when larger than any object of its class.

Pixel coordinates: ``x`` along columns, ``y`` along rows, box corners ``(x1, y1, x2, y2)``
in pixels of the original image with the top-left image corner at (0, 0) (so a box
covering pixel column 0 starts at x = 0 and one covering the last column ends at x = W).
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.shared.errors import ConfigError, GeometryError
from wardmap.shared.knowledge import KnowledgeGraph

__all__ = [
    "LETTERBOX_PAD",
    "YOLOX_STRIDES",
    "CocoMap",
    "DetectionLabels",
    "Detections",
    "MaskConfig",
    "decode_yolox",
    "detection_labels",
    "labels_from_detections",
    "letterbox",
    "nms_per_class",
]

F32 = NDArray[np.float32]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]
U16 = NDArray[np.uint16]

YOLOX_STRIDES: Final = (8, 16, 32)
"""Strides of the three YOLOX output grids, in input pixels."""
LETTERBOX_PAD: Final = 114
"""Grey value YOLOX pads letterboxed images with."""
PACKAGED_COCO_MAP: Final = "coco_to_kg.toml"
"""File name of the packaged COCO -> knowledge-graph map inside ``wardmap.shared.data``."""

_MAX_LOG_WH: Final = 20.0
"""Clip for the raw log-size outputs before ``exp`` (exp(20) * 32 px is beyond any image)."""
_NAME_KEY = re.compile(r"^[a-z][a-z0-9_]*$")


# ---------------------------------------------------------------------------- detections


@dataclass(frozen=True, eq=False)
class Detections:
    """Boxes found in one image, highest score first.

    Attributes:
        boxes_xyxy: float32 (K, 4) corners ``(x1, y1, x2, y2)`` in original image
            pixels, clipped to the image.
        scores: float32 (K,) objectness * class score in 0..1.
        coco_class: int64 (K,) detector class id (COCO 0..79 for COCO models).
        image_wh: ``(width, height)`` of the original image in pixels.
    """

    boxes_xyxy: F32
    scores: F32
    coco_class: I64
    image_wh: tuple[int, int]

    def __len__(self) -> int:
        return int(self.scores.shape[0])


def letterbox(bgr: ArrayLike, size: int = 416) -> tuple[F32, float]:
    """Resize keeping the aspect ratio and pad to ``size x size`` (YOLOX pre-processing).

    Args:
        bgr: uint8 (H, W, 3) image in BGR channel order.
        size: network input side length in pixels.

    Returns:
        ``(blob, ratio)``: a new float32 ``(1, 3, size, size)`` BGR blob with values
        0..255, the resized image at the top-left and :data:`LETTERBOX_PAD` elsewhere; and
        ``ratio = min(size / H, size / W)`` (input pixels per original pixel).

    Raises:
        GeometryError: not a uint8 (H, W, 3) image, or a non-positive size.
    """
    image = np.asarray(bgr)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3 or 0 in image.shape:
        raise GeometryError(f"letterbox: expected a uint8 (H, W, 3) BGR image, got {image.dtype} "
                            f"{image.shape}")
    if isinstance(size, bool) or not isinstance(size, int) or size <= 0:
        raise GeometryError(f"letterbox: size must be a positive integer, got {size!r}")
    H, W = image.shape[:2]
    ratio = min(size / H, size / W)
    new_w, new_h = max(1, int(W * ratio)), max(1, int(H * ratio))
    resized = cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    padded = np.full((size, size, 3), LETTERBOX_PAD, dtype=np.uint8)
    padded[:new_h, :new_w] = resized
    blob = np.ascontiguousarray(padded.transpose(2, 0, 1)[None], dtype=np.float32)
    return blob, float(ratio)


def _grids(input_size: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Cell offsets (A, 2) ``(x, y)`` and strides (A, 1) for the YOLOX grids of ``input_size``."""
    cells = []
    strides = []
    for stride in YOLOX_STRIDES:
        side = input_size // stride
        ys, xs = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
        cells.append(np.stack([xs.ravel(), ys.ravel()], axis=1))
        strides.append(np.full((side * side, 1), stride))
    return (np.concatenate(cells).astype(np.float32), np.concatenate(strides).astype(np.float32))


def _input_size_for(anchors: int) -> int | None:
    """Square input side S whose three grids have ``anchors`` cells in total, or None."""
    # A = S^2 (1/64 + 1/256 + 1/1024) = S^2 * 21 / 1024 for S a multiple of 32.
    side = round(math.sqrt(anchors * 1024 / 21))
    side -= side % 32
    for candidate in (side, side + 32):
        if candidate > 0 and sum((candidate // s) ** 2 for s in YOLOX_STRIDES) == anchors:
            return candidate
    return None


def decode_yolox(
    output: ArrayLike,
    ratio: float,
    image_wh: tuple[int, int],
    score_threshold: float = 0.3,
    nms_iou: float = 0.45,
) -> Detections:
    """Decode a raw YOLOX output into boxes in original image pixels.

    Args:
        output: float32 ``(1, A, 5 + C)`` raw grid outputs (module docstring); the input
            size S is inferred from A (A = 3549 -> S = 416).
        ratio: the letterbox ratio returned by :func:`letterbox`.
        image_wh: ``(width, height)`` of the original image; boxes are clipped to it.
        score_threshold: keep boxes with ``objectness * class score >= score_threshold``.
        nms_iou: per-class non-maximum suppression drops a box overlapping a
            higher-scoring box of the same class with IoU above this.

    Returns:
        :class:`Detections`, highest score first.

    Raises:
        GeometryError: on a wrong output shape, a non-positive ratio or image size, or
            thresholds outside 0..1.
    """
    raw = np.asarray(output)
    if raw.ndim != 3 or raw.shape[0] != 1 or raw.shape[2] < 6:
        raise GeometryError(f"decode_yolox: expected a (1, A, 5 + C) output, got {raw.shape}")
    input_size = _input_size_for(raw.shape[1])
    if input_size is None:
        raise GeometryError(f"decode_yolox: {raw.shape[1]} rows do not match the strides "
                            f"{YOLOX_STRIDES} of any square input (3549 for 416 x 416)")
    if not (math.isfinite(ratio) and ratio > 0):
        raise GeometryError(f"decode_yolox: ratio must be positive, got {ratio!r}")
    width, height = _check_wh(image_wh)
    for name, value in (("score_threshold", score_threshold), ("nms_iou", nms_iou)):
        if not 0.0 <= value <= 1.0:
            raise GeometryError(f"decode_yolox: {name} must lie in 0..1, got {value!r}")
    rows = raw[0].astype(np.float32, copy=False)
    class_scores = rows[:, 5:]
    best = np.argmax(class_scores, axis=1)
    scores = rows[:, 4] * class_scores[np.arange(rows.shape[0]), best]
    keep = np.flatnonzero(np.isfinite(scores) & (scores >= score_threshold))
    cells, strides = _grids(input_size)
    sel = rows[keep]
    xy = (sel[:, 0:2] + cells[keep]) * strides[keep]
    wh = np.exp(np.clip(sel[:, 2:4], -_MAX_LOG_WH, _MAX_LOG_WH)) * strides[keep]
    boxes = np.concatenate([xy - wh / 2, xy + wh / 2], axis=1) / np.float32(ratio)
    boxes[:, 0::2] = np.clip(boxes[:, 0::2], 0, width)
    boxes[:, 1::2] = np.clip(boxes[:, 1::2], 0, height)
    finite = np.all(np.isfinite(boxes), axis=1)
    area_ok = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
    ok = finite & area_ok
    boxes, kept_scores, kept_class = boxes[ok], scores[keep][ok], best[keep][ok].astype(np.int64)
    order = nms_per_class(boxes, kept_scores, kept_class, nms_iou)
    return Detections(
        boxes_xyxy=boxes[order].astype(np.float32),
        scores=kept_scores[order].astype(np.float32),
        coco_class=kept_class[order],
        image_wh=(width, height),
    )


def nms_per_class(boxes_xyxy: ArrayLike, scores: ArrayLike, classes: ArrayLike, iou_threshold: float) -> I64:
    """Greedy non-maximum suppression run separately for each class.

    Args:
        boxes_xyxy: (K, 4) box corners in pixels.
        scores: (K,) scores; higher wins.
        classes: (K,) integer class ids; boxes of different classes never suppress
            each other.
        iou_threshold: a box is dropped when its IoU with a kept, higher-scoring box of
            the same class is strictly greater than this.

    Returns:
        int64 indices of the kept boxes, highest score first (ties: lower index first).
    """
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    score = np.asarray(scores, dtype=np.float64).reshape(-1)
    cls = np.asarray(classes).reshape(-1)
    if not boxes.shape[0] == score.shape[0] == cls.shape[0]:
        raise GeometryError(f"nms_per_class: {boxes.shape[0]} boxes, {score.shape[0]} scores and "
                            f"{cls.shape[0]} classes must match")
    order = np.argsort(-score, kind="stable")
    x1, y1, x2, y2 = (boxes[:, k] for k in range(4))
    area = np.maximum(x2 - x1, 0) * np.maximum(y2 - y1, 0)
    suppressed = np.zeros(boxes.shape[0], dtype=bool)
    kept: list[int] = []
    for position, i in enumerate(order):
        if suppressed[i]:
            continue
        kept.append(int(i))
        rest = order[position + 1:]
        rest = rest[(cls[rest] == cls[i]) & ~suppressed[rest]]
        if rest.size == 0:
            continue
        inter_w = np.clip(np.minimum(x2[i], x2[rest]) - np.maximum(x1[i], x1[rest]), 0, None)
        inter_h = np.clip(np.minimum(y2[i], y2[rest]) - np.maximum(y1[i], y1[rest]), 0, None)
        inter = inter_w * inter_h
        union = area[i] + area[rest] - inter
        iou = np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)
        suppressed[rest[iou > iou_threshold]] = True
    return np.asarray(kept, dtype=np.int64)


# ---------------------------------------------------------------------------- class map


@dataclass(frozen=True, eq=False)
class CocoMap:
    """Detector classes and their knowledge-graph classes, from ``coco_to_kg.toml``.

    Attributes:
        names: detector class names; position = class id (COCO: 80 names, 0..79).
        to_kg: detector class id -> knowledge-graph class name, for mapped classes only;
            detections of other classes are ignored.
        source: where the map was read from, for messages.
        max_size_m: knowledge-graph class name -> the largest dimension, metres, of any object
            of the class (the file's ``[max_size_m]`` table); a mask that must be larger is not
            that object (:func:`labels_from_detections`). Classes not in it are not checked.
    """

    names: tuple[str, ...]
    to_kg: Mapping[int, str] = field(default_factory=lambda: MappingProxyType({}))
    source: str = "<coco map>"
    max_size_m: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))

    @classmethod
    def load(cls, path: str | Path | None = None) -> CocoMap:
        """Read and validate a class-map TOML file.

        Args:
            path: the file; ``None`` reads the packaged
                ``wardmap.shared.data/coco_to_kg.toml``.

        Raises:
            ConfigError: missing or malformed file, naming the file and entry at fault.
        """
        if path is None:
            source = f"wardmap.shared.data/{PACKAGED_COCO_MAP}"
            try:
                raw = resources.files("wardmap.shared.data").joinpath(PACKAGED_COCO_MAP).read_bytes()
            except OSError as exc:
                raise ConfigError(f"{source}: cannot read: {exc}") from exc
        else:
            file = Path(path)
            source = str(file)
            if not file.is_file():
                raise ConfigError(f"class-map file not found: {file}")
            try:
                raw = file.read_bytes()
            except OSError as exc:
                raise ConfigError(f"{source}: cannot read: {exc}") from exc
        try:
            data = tomllib.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"{source}: not valid UTF-8 TOML: {exc}") from exc
        return cls.from_mapping(data, source=source)

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], source: str = "<coco map>") -> CocoMap:
        """Build a map from parsed TOML: ``version = 1``, ``classes = [{id, name, kg?}, ...]``
        with ids 0..N-1 in order and unique names, and an optional ``[max_size_m]`` table of
        knowledge-graph class -> positive size in metres."""
        unknown = sorted(set(data) - {"version", "classes", "max_size_m"})
        if unknown:
            raise ConfigError(f"{source}: unknown key(s): {', '.join(unknown)}; allowed: version, classes, "
                              "max_size_m")
        if data.get("version") != 1 or isinstance(data.get("version"), bool):
            raise ConfigError(f"{source}: unsupported version {data.get('version')!r}; supported: 1")
        entries = data.get("classes")
        if not isinstance(entries, list) or not entries:
            raise ConfigError(f"{source}: classes must be a non-empty array of tables")
        names: list[str] = []
        to_kg: dict[int, str] = {}
        for position, entry in enumerate(entries):
            where = f"{source}: classes[{position}]"
            if not isinstance(entry, Mapping):
                raise ConfigError(f"{where}: expected a table {{id, name, kg}}, got {entry!r}")
            extra = sorted(set(entry) - {"id", "name", "kg"})
            if extra:
                raise ConfigError(f"{where}: unknown key(s): {', '.join(extra)}; allowed: id, name, kg")
            ident = entry.get("id")
            if isinstance(ident, bool) or ident != position:
                raise ConfigError(f"{where}: id must be {position} (ids follow list order), got {ident!r}")
            name = entry.get("name")
            if not isinstance(name, str) or not name.strip():
                raise ConfigError(f"{where}: name must be a non-empty string, got {name!r}")
            if name in names:
                raise ConfigError(f"{where}: duplicate class name {name!r}")
            names.append(name)
            if "kg" in entry:
                kg_name = entry["kg"]
                if not isinstance(kg_name, str) or not _NAME_KEY.match(kg_name):
                    raise ConfigError(f"{where}: kg must be a snake_case knowledge-graph class name, "
                                      f"got {kg_name!r}")
                to_kg[position] = kg_name
        sizes = data.get("max_size_m", {})
        if not isinstance(sizes, Mapping):
            raise ConfigError(f"{source}: max_size_m must be a table of class = metres, got {sizes!r}")
        max_size: dict[str, float] = {}
        for kg_name, value in sizes.items():
            if not _NAME_KEY.match(kg_name):
                raise ConfigError(f"{source}: max_size_m: {kg_name!r} is not a snake_case class name")
            if isinstance(value, bool) or not isinstance(value, int | float) or not (
                math.isfinite(value) and value > 0
            ):
                raise ConfigError(f"{source}: max_size_m.{kg_name} must be a positive number of metres, "
                                  f"got {value!r}")
            max_size[kg_name] = float(value)
        return cls(names=tuple(names), to_kg=MappingProxyType(to_kg), source=source,
                   max_size_m=MappingProxyType(max_size))

    def id_of(self, name: str) -> int:
        """Detector class id of ``name`` (e.g. ``"person"`` -> 0)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ConfigError(f"{self.source}: unknown detector class {name!r}") from None

    def kg_class(self, class_id: int) -> str | None:
        """Knowledge-graph class of detector class ``class_id``, or None when ignored."""
        return self.to_kg.get(int(class_id))

    def kg_lut(self, kg: KnowledgeGraph) -> NDArray[np.int16]:
        """Detector class id -> knowledge-graph class index, -1 for ignored classes.

        Raises:
            ConfigError: a mapped name is not a class of ``kg``.
        """
        lut = np.full(len(self.names), -1, dtype=np.int16)
        known = set(kg.names)
        strange = sorted(set(self.max_size_m) - known)
        if strange:
            raise ConfigError(f"{self.source}: max_size_m names {', '.join(strange)}, not knowledge-graph "
                              f"classes; known: {', '.join(kg.names)}")
        for class_id, kg_name in self.to_kg.items():
            if kg_name not in known:
                raise ConfigError(f"{self.source}: {self.names[class_id]!r} maps to {kg_name!r}, which "
                                  f"is not a knowledge-graph class; known: {', '.join(kg.names)}")
            lut[class_id] = kg.index_of(kg_name)
        return lut


# ---------------------------------------------------------------------------- label images


@dataclass(frozen=True)
class MaskConfig:
    """How :func:`labels_from_detections` turns a box into an instance mask.

    With depth, the object is taken to be the nearest dominant surface in its box:

    1. reference depth: a histogram of the box's valid depths, each pixel weighted by a
       Gaussian of its distance from the box centre (objects sit centred in their boxes,
       occluders and background at the sides), is summed over the depth band around every
       bin; the nearest bin whose band holds at least ``mode_fraction`` of the best band's
       weight (climbed to its local maximum) wins, and the median depth within its band is
       the reference;
    2. foreground: valid pixels within the band of the reference; pixels without depth
       (dark or shiny surfaces, out of range) join the foreground when the nearest valid
       pixel is foreground (distance transforms);
    3. cleaning: morphological opening then closing (never claiming pixels whose depth
       lies outside the band), keeping the largest connected part.

    Without depth, or with too little valid depth in the box, the shrunken box is filled.

    Masks are made smallest box first, and a box loses the pixels of the kept masks of
    smaller detections lying inside it (``inside_fraction``) before its depth is looked at:
    the box of a desk holds the cups on it, and its depth band would take them in.

    Size gate: a mask at reference depth ``z`` spanning ``n`` pixels (its longer bounding-box
    side) is at least ``n * z / f_max`` metres long, with ``f_max`` the focal length in pixels
    of the narrowest lens assumed (``min_hfov_deg``); when that exceeds the class's
    ``CocoMap.max_size_m``, the detection is not that object and paints nothing (an oblique
    monitor called a cup over a sixth of the image).
    """

    band_m: float = 0.4
    """Half-width of the depth band around the reference depth, in metres (a person is
    about 0.3-0.5 m deep)."""
    band_relative: float = 0.1
    """Relative half-width: the band is ``max(band_m, band_relative * depth)`` (depth noise
    of structured-light and ToF sensors grows with range)."""
    mode_fraction: float = 0.8
    """A nearer depth mode wins over the strongest one when its weight is at least this
    fraction of the strongest (1: always the strongest mode)."""
    center_sigma: float = 0.5
    """Standard deviation of the centre weighting, as a fraction of the box size."""
    bin_m: float = 0.05
    """Depth histogram bin width in metres."""
    min_valid_fraction: float = 0.1
    """Below this fraction of valid depth pixels in the box, the box is filled instead."""
    box_shrink: float = 0.1
    """Without usable depth the box scaled by ``1 - box_shrink`` about its centre is filled."""
    kernel_fraction: float = 0.04
    """Morphology kernel side as a fraction of the box's shorter side (3..15 px, odd)."""
    inside_fraction: float = 0.8
    """A smaller detection lies inside a larger one when this fraction of its box is inside
    the larger box; its mask is then cut out of the larger one."""
    min_hfov_deg: float = 45.0
    """Narrowest horizontal field of view, degrees, of the cameras the size gate must hold for
    (RGB-D cameras: 57-87 deg): it gives the smallest metric size a mask can have, so the gate
    never drops an object whose true size fits its class."""

    def __post_init__(self) -> None:
        if not 0.0 < self.mode_fraction <= 1.0:
            raise ConfigError(f"MaskConfig.mode_fraction must lie in (0, 1], got {self.mode_fraction!r}")
        if not 0.0 < self.inside_fraction <= 1.0:
            raise ConfigError(f"MaskConfig.inside_fraction must lie in (0, 1], got {self.inside_fraction!r}")
        if not 0.0 < self.min_hfov_deg < 180.0:
            raise ConfigError(f"MaskConfig.min_hfov_deg must lie in (0, 180), got {self.min_hfov_deg!r}")
        for name in ("min_valid_fraction", "box_shrink", "kernel_fraction", "band_relative"):
            value = getattr(self, name)
            if not 0.0 <= value < 1.0:
                raise ConfigError(f"MaskConfig.{name} must lie in [0, 1), got {value!r}")
        for name in ("band_m", "center_sigma", "bin_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"MaskConfig.{name} must be positive, got {value!r}")


@dataclass(frozen=True, eq=False)
class DetectionLabels:
    """Class and instance images painted from detections (:func:`detection_labels`).

    Attributes:
        class_image: uint8 (H, W) knowledge-graph class index (0 = background).
        instance_image: uint16 (H, W) instance id 1..K, in order of decreasing score over the
            detections used (0 = none).
        implausible: instance ids whose mask was larger than any object of their class
            (:class:`MaskConfig`, size gate); they paint nothing.
    """

    class_image: U8
    instance_image: U16
    implausible: tuple[int, ...] = ()


def labels_from_detections(*args: Any, **kwargs: Any) -> tuple[U8, U16]:
    """``(class_image, instance_image)`` of :func:`detection_labels` called with the same arguments."""
    labels = detection_labels(*args, **kwargs)
    return labels.class_image, labels.instance_image


def detection_labels(
    detections: Detections,
    coco_map: CocoMap,
    kg: KnowledgeGraph,
    depth_m: ArrayLike | None = None,
    *,
    min_score: float = 0.3,
    config: MaskConfig | None = None,
) -> DetectionLabels:
    """Paint class and instance images from detection boxes.

    Detections below ``min_score`` or of classes without a knowledge-graph class are
    ignored. Each remaining box becomes a mask, smallest box first: the box less the kept
    masks of smaller detections inside it (``MaskConfig.inside_fraction``), then with
    depth the nearest dominant surface in it (:class:`MaskConfig`), without depth (or with
    too little valid depth in the box) the shrunken box. A mask larger than any object of its
    class (``coco_map.max_size_m``, the size gate of :class:`MaskConfig`) is dropped and
    reported. Masks are painted farthest first, so nearer instances overwrite farther ones
    where they overlap (boxes without a depth reference count as farthest; among those,
    larger boxes first).

    Args:
        detections: boxes in pixels of an image of size ``detections.image_wh``.
        coco_map: detector class -> knowledge-graph class, and the classes' largest sizes.
        kg: the knowledge graph giving class indices.
        depth_m: float (H, W) depth in metres registered to the image (0, NaN, inf and
            negative = no data), or None (no size gate then).
        min_score: smallest detection score used.
        config: mask parameters (defaults: :class:`MaskConfig`).

    Returns:
        :class:`DetectionLabels`: new images and the ids of the implausible detections. An
        instance fully covered by nearer ones, or implausible, has no pixels.

    Raises:
        GeometryError: the depth image does not match ``detections.image_wh``.
        ConfigError: the class map names a class the knowledge graph lacks.
    """
    cfg = config or MaskConfig()
    width, height = _check_wh(detections.image_wh)
    depth: NDArray[np.float32] | None = None
    if depth_m is not None:
        depth = np.asarray(depth_m, dtype=np.float32)
        if depth.shape != (height, width):
            raise GeometryError(f"labels_from_detections: depth_m must be ({height}, {width}) to match "
                                f"the detections' image, got {depth.shape}")
    if kg.num_classes > 256:
        raise ConfigError(f"knowledge graph has {kg.num_classes} classes; a uint8 class image holds 256")
    lut = coco_map.kg_lut(kg)
    max_size = {kg.index_of(name): size for name, size in coco_map.max_size_m.items()}
    # Focal length in pixels of the narrowest lens assumed: the smallest metres per pixel.
    focal_max_px = (width / 2) / math.tan(math.radians(cfg.min_hfov_deg) / 2)
    class_image = np.zeros((height, width), dtype=np.uint8)
    instance_image = np.zeros((height, width), dtype=np.uint16)
    classes = detections.coco_class
    in_map = (classes >= 0) & (classes < lut.shape[0])
    kg_index = np.where(in_map, lut[np.clip(classes, 0, lut.shape[0] - 1)], -1)
    use = np.flatnonzero((kg_index > 0) & (detections.scores >= min_score))
    use = use[np.argsort(-detections.scores[use], kind="stable")]
    boxes: list[tuple[int, int, tuple[slice, slice]]] = []  # (area, instance id, region)
    for instance_id, k in enumerate(use[:65535], start=1):
        region = _box_region(detections.boxes_xyxy[k], width, height)
        if region is not None:
            rows, cols = region
            boxes.append(((rows.stop - rows.start) * (cols.stop - cols.start), instance_id, region))
    boxes.sort(key=lambda item: (item[0], item[1]))
    kept: list[tuple[float, int, int, int, tuple[slice, slice], NDArray[np.bool_]]] = []
    implausible: list[int] = []
    for area, instance_id, region in boxes:
        rows, cols = region
        exclude = _inner_masks(region, area, kept, cfg.inside_fraction)
        class_index = int(kg_index[use[instance_id - 1]])
        found = None if depth is None else _depth_mask(depth[rows, cols], cfg, exclude)
        if found is None:
            reference = math.inf
            mask = _shrunken_box(rows.stop - rows.start, cols.stop - cols.start, cfg) & ~exclude
        else:
            reference, mask = found
        if class_index in max_size and math.isfinite(reference) and mask.any():
            rows_used, cols_used = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
            extent_px = 1 + max(int(np.ptp(rows_used)), int(np.ptp(cols_used)))
            if extent_px * reference / focal_max_px > max_size[class_index]:
                implausible.append(instance_id)
                continue
        kept.append((reference, -area, instance_id, class_index, region, mask))
    kept.sort(key=lambda item: (-item[0], item[1], item[2]))
    for _, _, instance_id, class_index, region, mask in kept:
        class_image[region][mask] = class_index
        instance_image[region][mask] = instance_id
    return DetectionLabels(class_image, instance_image, tuple(sorted(implausible)))


def _inner_masks(
    region: tuple[slice, slice],
    area: int,
    kept: list[tuple[float, int, int, int, tuple[slice, slice], NDArray[np.bool_]]],
    inside_fraction: float,
) -> NDArray[np.bool_]:
    """bool (rows, cols) of ``region``: the pixels of kept masks of smaller boxes of which at
    least ``inside_fraction`` lies inside ``region``."""
    rows, cols = region
    out = np.zeros((rows.stop - rows.start, cols.stop - cols.start), dtype=bool)
    for _, minus_area, _, _, (r, c), mask in kept:
        if -minus_area >= area:
            continue
        r0, r1 = max(r.start, rows.start), min(r.stop, rows.stop)
        c0, c1 = max(c.start, cols.start), min(c.stop, cols.stop)
        if r1 <= r0 or c1 <= c0 or (r1 - r0) * (c1 - c0) < inside_fraction * -minus_area:
            continue
        out[r0 - rows.start : r1 - rows.start, c0 - cols.start : c1 - cols.start] |= mask[
            r0 - r.start : r1 - r.start, c0 - c.start : c1 - c.start
        ]
    return out


def _check_wh(image_wh: tuple[int, int]) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in image_wh)
    except (TypeError, ValueError):
        raise GeometryError(f"image_wh must be (width, height), got {image_wh!r}") from None
    if width <= 0 or height <= 0:
        raise GeometryError(f"image_wh must be positive, got {image_wh!r}")
    return width, height


def _box_region(box: NDArray[np.float32], width: int, height: int) -> tuple[slice, slice] | None:
    """Pixel rows and columns covered by a box (a pixel whose centre lies inside), or None."""
    x1, y1, x2, y2 = (float(v) for v in box)
    c0, c1 = max(0, math.ceil(x1 - 0.5)), min(width, math.ceil(x2 - 0.5))
    r0, r1 = max(0, math.ceil(y1 - 0.5)), min(height, math.ceil(y2 - 0.5))
    if c1 <= c0 or r1 <= r0:
        return None
    return slice(r0, r1), slice(c0, c1)


def _shrunken_box(rows: int, cols: int, cfg: MaskConfig) -> NDArray[np.bool_]:
    """A (rows, cols) mask of the box scaled by ``1 - box_shrink`` about its centre."""
    mask = np.zeros((rows, cols), dtype=bool)
    dr = round(rows * cfg.box_shrink / 2)
    dc = round(cols * cfg.box_shrink / 2)
    mask[dr:rows - dr, dc:cols - dc] = True
    if not mask.any():
        mask[:] = True
    return mask


def _depth_mask(
    depth_box: NDArray[np.float32], cfg: MaskConfig, exclude: NDArray[np.bool_]
) -> tuple[float, NDArray[np.bool_]] | None:
    """Reference depth and foreground mask of one box (:class:`MaskConfig`), or None when
    the box has too little valid depth. ``exclude`` (same shape): pixels of other objects,
    neither counted nor taken."""
    rows, cols = depth_box.shape
    valid = np.isfinite(depth_box) & (depth_box > 0) & ~exclude
    if np.count_nonzero(valid) < max(1.0, cfg.min_valid_fraction * rows * cols):
        return None
    # 1. reference depth: nearest strong mode of the centre-weighted depth histogram.
    yy = (np.arange(rows) + 0.5) / rows - 0.5
    xx = (np.arange(cols) + 0.5) / cols - 0.5
    weight = np.exp(-(yy[:, None] ** 2 + xx[None, :] ** 2) / (2 * cfg.center_sigma**2))
    values = depth_box[valid].astype(np.float64)
    low = float(values.min())
    bins = int((float(values.max()) - low) / cfg.bin_m) + 1
    bin_of = ((values - low) / cfg.bin_m).astype(np.intp)
    hist = np.bincount(bin_of, weights=weight[valid], minlength=bins)
    cumulative = np.concatenate([[0.0], np.cumsum(hist)])
    centers = low + (np.arange(bins) + 0.5) * cfg.bin_m
    bands = np.maximum(cfg.band_m, cfg.band_relative * centers)
    first = np.clip(np.floor((centers - bands - low) / cfg.bin_m).astype(np.intp), 0, bins)
    last = np.clip(np.floor((centers + bands - low) / cfg.bin_m).astype(np.intp) + 1, 0, bins)
    mass = cumulative[last] - cumulative[first]
    best = int(np.flatnonzero(mass >= cfg.mode_fraction * mass.max())[0])
    while best + 1 < bins and mass[best + 1] > mass[best]:
        best += 1
    end = best
    while end + 1 < bins and mass[end + 1] == mass[best]:
        end += 1
    best = (best + end) // 2  # the middle of a plateau of equal weight
    in_mode = np.abs(values - centers[best]) <= bands[best]
    if not in_mode.any():  # the band's bins hold values (mass > 0) just outside the exact band
        in_mode = (bin_of >= first[best]) & (bin_of < last[best])
    reference = float(np.median(values[in_mode]))
    # 2. foreground: in the band; pixels without depth follow their nearest valid pixel.
    band = max(cfg.band_m, cfg.band_relative * reference)
    foreground = valid & (np.abs(depth_box - reference) <= band)
    background = (valid & ~foreground) | exclude
    if background.any() and not valid.all():
        to_fg = cv2.distanceTransform((~foreground).astype(np.uint8), cv2.DIST_L2, 3)
        to_bg = cv2.distanceTransform((~background).astype(np.uint8), cv2.DIST_L2, 3)
        foreground |= ~valid & (to_fg <= to_bg)
    elif not background.any():
        foreground = np.ones_like(valid)
    # 3. cleaning: opening, closing (which may not claim pixels measured as background),
    #    largest connected part.
    mask = foreground.astype(np.uint8)
    side = min(15, max(3, round(cfg.kernel_fraction * min(rows, cols)) | 1))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (side, side))
    cleaned = cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel)
    cleaned = cv2.morphologyEx(cleaned, cv2.MORPH_CLOSE, kernel)
    cleaned[background] = 0
    count, components, stats, _ = cv2.connectedComponentsWithStats(cleaned, connectivity=8)
    if count <= 1:
        return reference, foreground & ~exclude
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return reference, components == largest
