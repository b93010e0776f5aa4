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
from dataclasses import dataclass
from typing import Any, Final

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
    "SegContract",
    "is_segmentation_model",
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

    def postprocess(self, logits: Any, image_hw: tuple[int, int], what: str) -> tuple[U8, F32]:
        """Per-pixel class uint8 (H, W) and softmax confidence float32 (H, W) at ``image_hw``.

        Raises:
            GeometryError: the logits do not have the contract's shape.
        """
        scores = np.asarray(logits, dtype=np.float32)
        w, h = self.input_wh
        want = (1, len(self.class_names), h, w)
        if scores.shape != want:
            raise GeometryError(f"{what}: output shape {scores.shape}, expected {want}")
        s = scores[0]
        classes = np.argmax(s, axis=0).astype(np.uint8)
        top = np.max(s, axis=0)
        confidence = (1.0 / np.sum(np.exp(s - top[None]), axis=0)).astype(np.float32)  # softmax max
        height, width = image_hw
        if (h, w) != (height, width):
            classes = cv2.resize(classes, (width, height), interpolation=cv2.INTER_NEAREST)
            confidence = cv2.resize(confidence, (width, height), interpolation=cv2.INTER_NEAREST)
        return classes, confidence


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
