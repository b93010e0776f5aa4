"""Logit adjustment of a segmentation network trained with class weights.

The network is trained with weighted cross-entropy (weights ``w_c`` up to 10x for rare
classes, :func:`wardmap.tools.training.segdata.class_weights`) so that rare classes
are learned at all. Weighting shifts the decision rule: the argmax then over-predicts
rare classes (a cup or a temperature gun on every cart). Post-hoc logit adjustment
(Menon et al., "Long-tail learning via logit adjustment", ICLR 2021) undoes a chosen
share of that shift: ``logits_c - alpha * log(w_c)``. ``alpha = 1`` is the full
correction for the weighting, 0 none; the strength is chosen on the held-out validation
worlds (seeds >= 1000), never on the benchmark's.

The bias is baked into the ONNX file as one ``Add`` after the network's output, so every
consumer (the server's perception stage, ``wardmap segment``, the edge's ``onnx:`` labels)
gets it with no code change, and it is recorded in the metadata key
``wardmap.logit_bias`` (JSON list, one number per class). A file that already has it is
refused (adjusting twice would double the shift).

Needs ``onnx`` (the ``train`` extra, or ``dev``) to edit the graph; no torch.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wardmap.shared.segmentation import INPUT_NAME, OUTPUT_NAME
from wardmap.tools.training.segdata import SegSamples, TrainingError, confusion, iou_from_confusion

META_LOGIT_BIAS = "wardmap.logit_bias"
"""ONNX metadata key recording a baked-in logit bias (JSON list of floats, one per class)."""


def adjustment_bias(weights: NDArray[np.floating], alpha: float) -> NDArray[np.float32]:
    """Per-class logit bias ``-alpha * log(w_c)`` (C,) for training class weights ``w`` (C,)."""
    w = np.asarray(weights, np.float64)
    if w.ndim != 1 or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise TrainingError(f"class weights must be a vector of positive numbers, got {w}")
    if not (np.isfinite(alpha) and 0.0 <= alpha <= 1.0):
        raise TrainingError(f"logit adjustment strength must be in [0, 1], got {alpha}")
    return (-alpha * np.log(w)).astype(np.float32)


def choose_alpha(
    logits: NDArray[np.floating], truth: NDArray[np.integer], weights: NDArray[np.floating],
    alphas: Sequence[float],
) -> tuple[float, dict[float, float]]:
    """The strength with the best mIoU on validation frames, and the mIoU (%) of each.

    Args:
        logits: (N, C, H, W) raw network outputs of the validation frames.
        truth: (N, H, W) class per pixel (values >= C are ignored).
        weights: (C,) training class weights.
        alphas: candidate strengths in [0, 1]; ties go to the smallest.

    mIoU is the mean over the classes present in the truth (the model card's definition).
    """
    if not alphas:
        raise TrainingError("no logit adjustment strengths to choose from")
    n = logits.shape[1]
    scores: dict[float, float] = {}
    for a in sorted({float(x) for x in alphas}):
        bias = adjustment_bias(weights, a)
        cm = np.zeros((n, n), np.int64)
        for lg, t in zip(logits, truth, strict=True):
            cm += confusion(np.argmax(lg.astype(np.float32) + bias[:, None, None], axis=0), t, n)
        iou = iou_from_confusion(cm)
        present = cm.sum(1) > 0
        scores[a] = float(np.mean(iou[present]) * 100.0)
    best = max(scores, key=lambda a: (scores[a], -a))
    return best, scores


def onnx_logits(
    session: Any, rgb: NDArray[np.uint8], depth_mm: NDArray[np.uint16] | None = None
) -> NDArray[np.float32]:
    """Logits (1, C, H, W) of one uint8 (H, W, 3) RGB image through an onnxruntime session.

    An RGB-D model (4 input channels) also gets ``depth_mm`` (H, W) uint16 millimetres.
    """
    x = (rgb.astype(np.float32) / 255.0).transpose(2, 0, 1)[None]
    if session.get_inputs()[0].shape[1] == 4:
        if depth_mm is None:
            raise ValueError("an RGB-D segmentation model needs a depth image")
        x = np.concatenate([x, (depth_mm.astype(np.float32) / np.float32(1000.0))[None, None]], axis=1)
    out = session.run([OUTPUT_NAME], {INPUT_NAME: np.ascontiguousarray(x)})[0]
    return np.asarray(out, np.float32)


def val_logits(path: Path, samples: SegSamples, threads: int = 1) -> NDArray[np.float16]:
    """Raw logits (N, C, H, W) of ``samples`` through the ONNX model at ``path`` (float16)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    pairs = zip(samples.rgb, samples.depth, strict=True)
    return np.stack([onnx_logits(sess, rgb, depth)[0].astype(np.float16) for rgb, depth in pairs])


def add_logit_bias(src: Path, dst: Path, bias: NDArray[np.floating]) -> None:
    """Write ``src`` to ``dst`` with ``logits + bias`` as its output (see module docstring).

    Raises:
        TrainingError: onnx missing, ``src`` unreadable, not in the contract (one output
            named ``logits`` with C channels), or already adjusted.
    """
    try:
        import onnx
        from onnx import helper, numpy_helper
    except ImportError as exc:
        raise TrainingError("onnx is not installed; pip install -e '.[train]'") from exc
    try:
        model = onnx.load(str(src))
    except Exception as exc:  # onnx raises several types for unreadable files
        raise TrainingError(f"cannot read {src}: {exc}") from exc
    meta = {p.key: p.value for p in model.metadata_props}
    if META_LOGIT_BIAS in meta:
        raise TrainingError(f"{src} already has a logit bias ({META_LOGIT_BIAS}); adjust the raw model")
    graph = model.graph
    outs = [o for o in graph.output if o.name == OUTPUT_NAME]
    if len(graph.output) != 1 or not outs:
        raise TrainingError(f"{src}: expected one output named {OUTPUT_NAME!r}")
    dims = [d.dim_value for d in outs[0].type.tensor_type.shape.dim]
    b = np.asarray(bias, np.float32).reshape(-1)
    if len(dims) != 4 or dims[1] != b.size:
        raise TrainingError(f"{src}: output shape {dims} does not have {b.size} channels")
    for node in graph.node:
        node.output[:] = ["logits_raw" if o == OUTPUT_NAME else o for o in node.output]
        node.input[:] = ["logits_raw" if i == OUTPUT_NAME else i for i in node.input]
    graph.initializer.append(numpy_helper.from_array(b.reshape(1, -1, 1, 1), "logit_bias"))
    add = helper.make_node("Add", ["logits_raw", "logit_bias"], [OUTPUT_NAME], name="logit_adjust")
    graph.node.append(add)
    entry = model.metadata_props.add()
    entry.key, entry.value = META_LOGIT_BIAS, json.dumps([round(float(x), 6) for x in b])
    onnx.checker.check_model(model)
    tmp = dst.with_suffix(".tmp.onnx")
    onnx.save(model, str(tmp))
    tmp.replace(dst)


def adjust_model(
    src: Path, dst: Path, val: SegSamples, weights: NDArray[np.floating], alphas: Sequence[float],
    threads: int = 1,
) -> dict[str, Any]:
    """Choose the strength on ``val`` and write the adjusted model; returns what was done:
    ``alpha``, ``bias`` (list), ``val_miou_by_alpha`` ({alpha: %}). With the best strength
    0 the model is copied unchanged (no metadata added)."""
    alpha, scores = choose_alpha(val_logits(src, val, threads), val.classes, weights, alphas)
    bias = adjustment_bias(weights, alpha)
    if alpha > 0:
        add_logit_bias(src, dst, bias)
    elif src != dst:
        dst.write_bytes(src.read_bytes())
    return {
        "alpha": alpha,
        "bias": [round(float(x), 4) for x in bias],
        "val_miou_by_alpha": {str(a): round(s, 2) for a, s in scores.items()},
    }


__all__ = [
    "META_LOGIT_BIAS",
    "add_logit_bias",
    "adjust_model",
    "adjustment_bias",
    "choose_alpha",
    "onnx_logits",
    "val_logits",
]
