"""The ONNX contract of wardmap segmentation networks: checks, pre- and post-processing.

Pure numpy/OpenCV, shared by every runtime that runs such a network: the server's
perception (``wardmap.server.perception.models.OnnxSegmenter``) and the edge's label source
(``wardmap.edge.labels``, ``onnx:PATH`` with a segmentation model). The onnxruntime session
lives in each of them.

Contract (what ``wardmap train-seg`` exports):

- one input ``image``: float32 ``[1, 3, H, W]``, RGB, values 0..1 (any normalisation is
  inside the model); or ``[1, 4, H, W]`` for an RGB-D network: RGB 0..1 and, as the fourth
  channel, depth in metres along the camera z axis, 0 where the sensor has none (depth is
  resized to the input size by nearest neighbour, so holes stay holes);
- one output ``logits``: float32 ``[1, C, H, W]``, C = 1 + the knowledge graph's classes
  (index 0 background, index i = the i-th ``[[classes]]`` of
  ``shared/data/knowledge_graph.toml``, so a class map is directly a knowledge-graph class
  image);
- metadata ``wardmap.classes``: JSON list of the C class names in index order (first
  ``"background"``), and ``wardmap.input_size``: ``"WxH"`` (e.g. ``"320x240"``).
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final, NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.shared.errors import ConfigError, GeometryError
from wardmap.shared.knowledge import BACKGROUND, KnowledgeGraph

__all__ = [
    "INPUT_NAME",
    "META_CLASSES",
    "META_INPUT_SIZE",
    "OUTPUT_NAME",
    "Decoded",
    "PlacementRule",
    "SegContract",
    "argmax_classes",
    "drop_unsure_regions",
    "is_segmentation_model",
    "upsample_classes",
]

U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]

INPUT_NAME: Final = "image"
OUTPUT_NAME: Final = "logits"
META_CLASSES: Final = "wardmap.classes"
META_INPUT_SIZE: Final = "wardmap.input_size"
_SIZE = re.compile(r"^\s*(\d+)\s*x\s*(\d+)\s*$")


def is_segmentation_model(metadata: Mapping[str, str]) -> bool:
    """True when a model's metadata declares it a wardmap segmentation network."""
    return META_CLASSES in metadata


@dataclass(frozen=True)
class SegContract:
    """A checked segmentation network: its classes and input size.

    Attributes:
        class_names: the C class names, index order, ``"background"`` first.
        input_wh: ``(width, height)`` the network runs at.
        depth_input: True for an RGB-D network (4 input channels): it needs the depth image.
    """

    class_names: tuple[str, ...]
    input_wh: tuple[int, int]
    depth_input: bool = False

    @staticmethod
    def check(
        metadata: Mapping[str, str],
        inputs: Sequence[tuple[str, Sequence[Any]]],
        outputs: Sequence[tuple[str, Sequence[Any]]],
        kg: KnowledgeGraph,
        what: str,
    ) -> SegContract:
        """Check a model against the contract.

        Args:
            metadata: the model's custom metadata.
            inputs, outputs: ``(name, shape)`` of each; symbolic dimensions (str, None) pass.
            kg: the knowledge graph the classes must match.
            what: names the model in messages (e.g. ``"segmentation model /path/x.onnx"``).

        Raises:
            ConfigError: missing or malformed metadata, classes that differ from the knowledge
                graph's, wrong input/output names or shapes.
        """
        names = _check_classes(metadata, kg, what)
        w, h = _check_size(metadata, what)
        input_names = [n for n, _ in inputs]
        if input_names != [INPUT_NAME]:
            raise ConfigError(f"{what}: expected one input named {INPUT_NAME!r}, got {input_names}")
        out_names = [n for n, _ in outputs]
        if OUTPUT_NAME not in out_names:
            raise ConfigError(f"{what}: expected an output named {OUTPUT_NAME!r}, got {out_names}")
        in_shape = list(inputs[0][1])
        channels = in_shape[1] if len(in_shape) == 4 and in_shape[1] in (3, 4) else 3
        _check_shape(what, f"input {INPUT_NAME!r}", in_shape, [1, channels, h, w])
        out_shape = list(outputs[out_names.index(OUTPUT_NAME)][1])
        _check_shape(what, f"output {OUTPUT_NAME!r}", out_shape, [1, len(names), h, w])
        return SegContract(names, (w, h), depth_input=channels == 4)

    def preprocess(self, bgr: U8, depth_m: F32 | None = None) -> F32:
        """The network input ``[1, 3, h, w]`` float32 RGB 0..1 of a uint8 (H, W, 3) BGR image;
        ``[1, 4, h, w]`` with the depth (H, W) float32 metres (0 = no data) for an RGB-D network.

        Raises:
            GeometryError: a malformed image; an RGB-D network without a depth image of the
                image's size.
        """
        image = np.asarray(bgr)
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3 or 0 in image.shape:
            raise GeometryError(f"segment: expected a uint8 (H, W, 3) BGR image, got {image.dtype} "
                                f"{image.shape}")
        w, h = self.input_wh
        interp = cv2.INTER_AREA if w < image.shape[1] else cv2.INTER_LINEAR
        rgb = cv2.cvtColor(cv2.resize(image, (w, h), interpolation=interp), cv2.COLOR_BGR2RGB)
        x = np.ascontiguousarray(rgb.transpose(2, 0, 1)[None], dtype=np.float32) / np.float32(255.0)
        if not self.depth_input:
            return x
        if depth_m is None:
            raise GeometryError("segment: this is an RGB-D network; it needs the frame's depth image")
        depth = np.asarray(depth_m, np.float32)
        if depth.shape != image.shape[:2]:
            raise GeometryError(f"segment: depth has shape {depth.shape}, the image {image.shape[:2]}")
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0.0)).astype(np.float32)
        small = cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
        return np.ascontiguousarray(np.concatenate([x, small[None, None]], axis=1), np.float32)

    def decode(
        self,
        logits: Any,
        image_hw: tuple[int, int],
        what: str,
        *,
        placement: PlacementRule | None = None,
        refine_edges: bool = True,
        min_region_confidence: float = 0.0,
    ) -> Decoded:
        """Class maps and confidence at ``image_hw`` of the network output.

        Args:
            logits: the network output ``[1, C, h, w]``.
            image_hw: the size of the image the classes are for.
            what: names the model in messages.
            placement: the knowledge graph's placement check (:class:`PlacementRule`), or
                None for none.
            refine_edges: when ``image_hw`` differs from the input size, take the class
                of a pixel on a class boundary from the bilinearly upsampled logits
                (:func:`upsample_classes`) in ``classes``; ``nearest`` always holds each
                pixel's nearest network cell's class.
            min_region_confidence: a connected region of a class other than background
                (8-connected, network cells) whose mean softmax confidence is lower takes
                each cell's next most likely class (:func:`drop_unsure_regions`), before the
                placement check; 0 turns it off.

        Raises:
            GeometryError: the logits do not have the contract's shape.
            ConfigError: ``min_region_confidence`` outside 0..1.
        """
        scores = np.asarray(logits, dtype=np.float32)
        w, h = self.input_wh
        want = (1, len(self.class_names), h, w)
        if scores.shape != want:
            raise GeometryError(f"{what}: output shape {scores.shape}, expected {want}")
        if not 0.0 <= min_region_confidence <= 1.0:
            raise ConfigError(f"{what}: min_region_confidence must lie in 0..1, got {min_region_confidence}")
        s = scores[0]
        classes, top = argmax_classes(s)
        confidence: F32 | None = None
        if min_region_confidence > 0:
            s, classes, top, confidence = drop_unsure_regions(s, classes, top, min_region_confidence)
        if placement is not None:
            vetoed, classes = placement.apply(s, classes)
            if vetoed is not s:  # apply's classes are the argmax of the vetoed scores
                s = vetoed
                top = np.take_along_axis(s, classes[None].astype(np.intp), axis=0)[0]
                confidence = None
        if confidence is None:
            confidence = _top_softmax(s, top)
        height, width = image_hw
        if (h, w) == (height, width):
            return Decoded(classes, classes, confidence)
        size = (width, height)
        nearest: U8 = np.asarray(cv2.resize(classes, size, interpolation=cv2.INTER_NEAREST), np.uint8)
        confidence = np.asarray(cv2.resize(confidence, size, interpolation=cv2.INTER_NEAREST), np.float32)
        refined = upsample_classes(s, classes, image_hw, nearest) if refine_edges else nearest
        return Decoded(refined, nearest, confidence)


def _top_softmax(scores: F32, top: F32) -> F32:
    """Softmax (h, w) of the chosen class, its score ``top`` (h, w), among scores (C, h, w);
    a vetoed class (``-inf``) adds nothing."""
    exp = scores - top[None]
    np.exp(exp, out=exp)
    return (1.0 / exp.sum(axis=0)).astype(np.float32)


def drop_unsure_regions(
    scores: F32, classes: U8, top: F32, min_confidence: float, confidence: F32 | None = None
) -> tuple[F32, U8, F32, F32]:
    """Veto the class of every unsure region: ``(scores, classes, top, confidence)`` after it.

    A region is an 8-connected component of one class other than background (index 0) in
    ``classes`` (h, w), the argmax of ``scores`` (C, h, w) with maximum ``top`` (h, w) and
    softmax ``confidence`` (h, w; computed when None). A region is unsure when the mean, over
    its cells, of the network's softmax for its class is below ``min_confidence``; that class
    then gets ``-inf`` on the region and each cell takes its next most likely class. The
    classes that gained cells are checked again, each cell still judged by the network's own
    softmax for its new class (never renormalised, so a veto cannot make a class look surer
    than the network was), until no region is unsure: a speck joins a sure neighbouring
    region of its next class, or falls through to background, which is never vetoed. The
    returned confidence of a vetoed cell is its new class's softmax among the classes left,
    as after the placement check. A network hesitating between classes leaves such specks (a
    cup on a sink's tap); a whole object seen clearly is not one. Only classes with a cell
    below ``min_confidence`` can hold an unsure region, so only they are looked at. Returns
    the inputs themselves when nothing is vetoed.
    """
    if confidence is None:
        confidence = _top_softmax(scores, top)
    judge = confidence  # the network's softmax of each cell's current class
    out, copied = scores, False
    check = np.unique(classes[confidence < min_confidence])
    while True:  # ends: each round sets some finite non-background score to -inf
        vetoed = np.zeros(classes.shape, bool)
        for c in check[check > 0]:
            here = classes == c
            n, regions = cv2.connectedComponents(here.astype(np.uint8), connectivity=8)
            labels = regions[here]
            total = np.bincount(labels, weights=judge[here], minlength=n)
            unsure = total < min_confidence * np.bincount(labels, minlength=n)  # mean < min_confidence
            unsure[0] = False  # label 0: the cells of other classes
            if not unsure.any():
                continue
            if out is scores:
                out = scores.copy()
            cells = unsure[regions]
            out[c][cells] = -np.inf
            vetoed |= cells
        if not vetoed.any():
            break
        if not copied:  # the caller's arrays stay as they were
            classes, top, confidence, judge = classes.copy(), top.copy(), confidence.copy(), judge.copy()
            copied = True
        left = out[:, vetoed]  # (C, k): the vetoed cells' scores, vetoed classes -inf
        best = np.argmax(left, axis=0)  # ties to the lower class, as argmax_classes
        k = np.arange(left.shape[1])
        high = left[best, k]
        classes[vetoed] = best.astype(np.uint8)
        top[vetoed] = high
        confidence[vetoed] = 1.0 / np.exp(left - high[None]).sum(axis=0)
        own = scores[:, vetoed]
        peak = own.max(axis=0)
        judge[vetoed] = np.exp(own[best, k] - peak) / np.exp(own - peak[None]).sum(axis=0)
        check = np.unique(best)
    return out, classes, top, confidence


class Decoded(NamedTuple):
    """A decoded network output at the image's size.

    Attributes:
        classes: (H, W) uint8 class per pixel; on class boundaries from the bilinearly
            upsampled logits when refined (:meth:`SegContract.decode`).
        nearest: (H, W) uint8 class of each pixel's nearest network cell (``classes`` itself
            when not refined or at the network's size).
        confidence: (H, W) float32 softmax of the cell's class, nearest cell.
    """

    classes: U8
    nearest: U8
    confidence: F32


_PLACED_ON: Final = "placed_on"
_HELD_BY: Final = ("carries", "operates")


@dataclass(frozen=True)
class PlacementRule:
    """Where the knowledge graph lets an object be seen (paper 001 Sec. 3.2, ``placed_on``).

    A class with ``placed_on`` facts (cups and temperature guns: on desks, cabinets and carts)
    rests on one of those objects or is held by an entity that ``carries`` or ``operates``
    it (a person). A connected region of such a class in the network's class map with none
    of those classes within ``ring_px`` network pixels around it (regions of other checked
    classes do not count) contradicts the graph: its pixels take their next most likely
    class. A network that paints cups on a sink's tap, or a temperature gun on a wall, then
    does not report one.

    Attributes:
        supports: checked class index -> the class indices that may touch its regions.
        ring_px: width of the ring searched around a region, network pixels.
    """

    supports: Mapping[int, frozenset[int]]
    ring_px: int = 3
    _allowed: dict[int, NDArray[np.bool_]] = field(init=False, repr=False, compare=False)
    _kernel: U8 = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Per checked class: a lookup over every uint8 class index, True where it may touch.
        allowed = {}
        for c, ok in self.supports.items():
            table = np.zeros(256, bool)
            table[list(ok)] = True
            allowed[c] = table
        object.__setattr__(self, "_allowed", allowed)
        object.__setattr__(self, "_kernel", np.ones((2 * self.ring_px + 1,) * 2, np.uint8))

    @staticmethod
    def from_knowledge(kg: KnowledgeGraph, class_names: Sequence[str], ring_px: int = 3) -> PlacementRule:
        """The rule for a network with ``class_names`` (index order, background first).

        Raises:
            ConfigError: ``ring_px`` < 1.
        """
        if ring_px < 1:
            raise ConfigError(f"placement check: ring_px must be >= 1, got {ring_px}")
        supports: dict[int, frozenset[int]] = {}
        for name in class_names[1:]:
            on = {r.object for r in kg.relations(subject=name, predicate=_PLACED_ON)}
            if not on:
                continue
            held = {r.subject for p in _HELD_BY for r in kg.relations(predicate=p, object=name)}
            supports[class_names.index(name)] = frozenset(
                class_names.index(c) for c in sorted(on | held) if c in class_names)
        return PlacementRule(supports, ring_px)

    def apply(self, scores: F32, classes: U8 | None = None) -> tuple[F32, U8]:
        """Scores (C, h, w) with ``-inf`` for each checked class on its regions without
        support, and their argmax (h, w) uint8.

        ``classes``: the argmax of ``scores``, when the caller has it. Repeats until no
        region is vetoed (a vetoed region may turn into another checked class); returns
        ``scores`` itself when nothing is vetoed.
        """
        if classes is None:
            classes, _ = argmax_classes(scores)
        out = scores
        for _ in range(len(self._allowed) + 1):
            vetoed = False
            for c, table in self._allowed.items():
                here = (classes == c).astype(np.uint8)
                if not here.any():
                    continue
                n, regions = cv2.connectedComponents(here, connectivity=8)
                for k in range(1, n):
                    region = regions == k
                    ring = cv2.dilate(region.astype(np.uint8), self._kernel).astype(bool) & ~region
                    if table[classes[ring]].any():
                        continue
                    if out is scores:
                        out = scores.copy()
                    out[c][region] = -np.inf
                    vetoed = True
            if not vetoed:
                break
            classes, _ = argmax_classes(out)
        return out, classes


def argmax_classes(scores: F32) -> tuple[U8, F32]:
    """Argmax (h, w) uint8 and maximum (h, w) of scores (C, h, w), C <= 256; ties go to the
    lower class. One pass per class: several times faster than ``np.argmax`` over axis 0."""
    best = scores[0].copy()
    classes = np.zeros(best.shape, np.uint8)
    for c in range(1, len(scores)):
        higher = scores[c] > best
        np.copyto(best, scores[c], where=higher)
        classes[higher] = c
    return classes, best


def upsample_classes(scores: F32, classes: U8, image_hw: tuple[int, int], nearest: U8 | None = None) -> U8:
    """Classes (H, W) at ``image_hw`` of a network's scores (C, h, w) and their argmax (h, w);
    ``nearest``: the argmax resized to ``image_hw`` by nearest neighbour, when the caller
    has it (not modified).

    The argmax of the bilinearly upsampled scores, computed only where it can differ from
    the nearest cell's class: a pixel whose four neighbouring cells share a class keeps it
    (a convex combination of scores that all favour one class favours it too). On a class
    boundary the pixel takes, of its four cells' classes, the one with the highest
    interpolated score, so no class appears that none of its cells has. Pixel centres are
    aligned as ``cv2.resize`` aligns them.
    """
    height, width = image_hw
    h, w = classes.shape
    if nearest is None:
        nearest = np.asarray(cv2.resize(classes, (width, height), interpolation=cv2.INTER_NEAREST), np.uint8)
    out: U8 = nearest.copy()
    kernel = np.ones((3, 3), np.uint8)
    boundary = cv2.dilate(classes, kernel) != cv2.erode(classes, kernel)
    if not boundary.any():
        return out
    near = cv2.resize(boundary.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST)
    ys, xs = np.nonzero(near)
    fx = (xs + 0.5) * (w / width) - 0.5
    fy = (ys + 0.5) * (h / height) - 0.5
    x0 = np.clip(np.floor(fx).astype(np.int64), 0, max(w - 2, 0))
    y0 = np.clip(np.floor(fy).astype(np.int64), 0, max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    ax = np.clip(fx - x0, 0.0, 1.0).astype(np.float32)
    ay = np.clip(fy - y0, 0.0, 1.0).astype(np.float32)
    cells = ((y0, x0), (y0, x1), (y1, x0), (y1, x1))
    weights = ((1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay)
    best = np.full(len(ys), -np.inf, np.float32)
    for cy, cx in cells:  # each cell's class is a candidate; score it at the pixel
        candidate = classes[cy, cx]
        value = np.zeros(len(ys), np.float32)
        for (qy, qx), weight in zip(cells, weights, strict=True):
            cell = scores[candidate, qy, qx]
            value += np.where(np.isfinite(cell), cell, np.float32(-1e30)) * weight
        better = value > best
        best[better] = value[better]
        out[ys[better], xs[better]] = candidate[better]
    return out


def _check_classes(meta: Mapping[str, str], kg: KnowledgeGraph, what: str) -> tuple[str, ...]:
    if META_CLASSES not in meta:
        raise ConfigError(f"{what}: metadata {META_CLASSES!r} (JSON list of class names) is missing")
    try:
        names = json.loads(meta[META_CLASSES])
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{what}: metadata {META_CLASSES!r} is not JSON: {exc}") from exc
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise ConfigError(f"{what}: metadata {META_CLASSES!r} must be a JSON list of strings")
    expected = [BACKGROUND, *kg.names]
    if names != expected:
        diff = next(
            (i for i, (a, b) in enumerate(zip(names, expected, strict=False)) if a != b),
            min(len(names), len(expected)),
        )
        got = names[diff] if diff < len(names) else "(none)"
        want = expected[diff] if diff < len(expected) else "(none)"
        raise ConfigError(
            f"{what}: its {len(names)} classes do not match the knowledge graph's "
            f"{len(expected)} (background + classes): index {diff} is {got!r}, expected {want!r}"
        )
    return tuple(names)


def _check_size(meta: Mapping[str, str], what: str) -> tuple[int, int]:
    match = _SIZE.match(meta.get(META_INPUT_SIZE, ""))
    if match is None:
        raise ConfigError(
            f"{what}: metadata {META_INPUT_SIZE!r} must be 'WxH' (e.g. '320x240'), "
            f"got {meta.get(META_INPUT_SIZE)!r}"
        )
    w, h = int(match.group(1)), int(match.group(2))
    if w < 1 or h < 1:
        raise ConfigError(f"{what}: input size {w}x{h} must be positive")
    return w, h


def _check_shape(what: str, name: str, shape: list[Any], expected: list[int]) -> None:
    """Fixed dimensions must equal ``expected``; symbolic ones (strings, None) pass."""
    ok = len(shape) == len(expected) and all(
        not isinstance(d, int) or d == e for d, e in zip(shape, expected, strict=True)
    )
    if not ok:
        raise ConfigError(f"{what}: {name} has shape {shape}, expected {expected}")
