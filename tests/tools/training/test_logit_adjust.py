"""Post-hoc logit adjustment (``tools/training/logit_adjust.py``): bias, choice, ONNX edit."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnx", reason="editing ONNX graphs needs the onnx package (dev dependency)")
import onnx
import onnxruntime as ort

from wardmap.server.perception.models import make_segmenter
from wardmap.tools.training.logit_adjust import (
    META_LOGIT_BIAS,
    add_logit_bias,
    adjust_model,
    adjustment_bias,
    choose_alpha,
)
from wardmap.tools.training.segdata import SegSamples, TrainingError, class_weights

HELPER = Path(__file__).resolve().parents[2] / "server" / "perception" / "tiny_onnx.py"
_spec = importlib.util.spec_from_file_location("tiny_onnx", HELPER)
assert _spec is not None and _spec.loader is not None
tiny = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(tiny)
kg_classes, write_tiny_seg = tiny.kg_classes, tiny.write_tiny_seg


def test_class_weights_favour_rare_classes() -> None:
    """Rarer classes weigh more; absent classes get the maximum; weights are clipped."""
    cls = np.zeros(1000, np.uint8)
    cls[:10] = 1
    cls[10:300] = 2
    w = class_weights(cls, 4, 0.5, 10.0)
    assert w[1] > w[2] > w[0]
    assert w[3] == 10.0 and w.max() <= 10.0 and w.min() >= 0.1


def test_adjustment_bias_undoes_the_weights_in_log_space() -> None:
    w = np.array([0.5, 1.0, 4.0])
    np.testing.assert_allclose(adjustment_bias(w, 1.0), -np.log(w), rtol=1e-6)
    np.testing.assert_allclose(adjustment_bias(w, 0.5), -0.5 * np.log(w), rtol=1e-6)
    assert not adjustment_bias(w, 0.0).any()
    with pytest.raises(TrainingError, match=r"in \[0, 1\]"):
        adjustment_bias(w, 1.5)
    with pytest.raises(TrainingError, match="positive"):
        adjustment_bias(np.array([1.0, 0.0]), 0.5)


def test_choose_alpha_picks_the_strength_that_stops_rare_class_false_positives() -> None:
    """Class 1 (rare, weight 8) wins pixels of class 0 by a margin below log 8: only a
    strong enough adjustment gives them back; a tie goes to the weaker strength."""
    rng = np.random.default_rng(0)
    truth = np.zeros((4, 8, 8), np.int64)
    truth[:, :2, :2] = 1
    logits = np.zeros((4, 2, 8, 8), np.float32)
    logits[:, 1] = np.where(truth == 1, 3.0, 1.5) + rng.normal(0, 0.1, truth.shape)
    weights = np.array([1.0, 8.0])  # log 8 = 2.08: alpha 1 moves 1.5 below 0, keeps 3.0 above
    alpha, scores = choose_alpha(logits, truth, weights, (0.0, 0.5, 1.0))
    assert scores[0.0] == scores[0.5] < scores[1.0] == pytest.approx(100.0)  # half is not enough
    assert alpha == 1.0
    same = np.zeros_like(logits)
    same[:, 0] = np.where(truth == 0, 5.0, -5.0)
    assert choose_alpha(same, truth, weights, (0.0, 0.5, 1.0))[0] == 0.0


def _run(path: Path, x: np.ndarray) -> np.ndarray:
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return np.asarray(sess.run(["logits"], {"image": x})[0])


def test_add_logit_bias_adds_it_inside_the_model(tmp_path: Path) -> None:
    raw = write_tiny_seg(tmp_path / "raw.onnx")
    n = len(kg_classes())
    bias = np.linspace(-1.0, 1.0, n).astype(np.float32)
    add_logit_bias(raw, tmp_path / "adj.onnx", bias)
    x = np.random.default_rng(1).random((1, 3, 24, 32), dtype=np.float32)
    expected = _run(raw, x) + bias[None, :, None, None]
    np.testing.assert_allclose(_run(tmp_path / "adj.onnx", x), expected, atol=1e-5)
    meta = {p.key: p.value for p in onnx.load(str(tmp_path / "adj.onnx")).metadata_props}
    np.testing.assert_allclose(json.loads(meta[META_LOGIT_BIAS]), bias, atol=1e-6)
    assert "wardmap.classes" in meta
    make_segmenter(f"model:{tmp_path / 'adj.onnx'}", threads=1)  # still in the contract
    with pytest.raises(TrainingError, match="already has a logit bias"):
        add_logit_bias(tmp_path / "adj.onnx", tmp_path / "twice.onnx", bias)
    with pytest.raises(TrainingError, match="channels"):
        add_logit_bias(raw, tmp_path / "bad.onnx", bias[:-1])
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(TrainingError, match="cannot read"):
        add_logit_bias(tmp_path / "junk.onnx", tmp_path / "bad.onnx", bias)
    assert not (tmp_path / "bad.onnx").exists() and not (tmp_path / "twice.onnx").exists()


def test_adjust_model_keeps_a_model_that_needs_none(tmp_path: Path) -> None:
    """With strength 0 the best (or the only candidate) the file is copied unchanged."""
    raw = write_tiny_seg(tmp_path / "raw.onnx")
    names = tuple(kg_classes())
    rgb = np.zeros((2, 24, 32, 3), np.uint8)
    rgb[:, :12] = (255, 0, 0)  # red: person in the tiny model
    truth = np.zeros((2, 24, 32), np.uint8)
    truth[:, :12] = names.index("person")
    no_depth = np.zeros(truth.shape, np.uint16)
    val = SegSamples(rgb, truth, no_depth, np.zeros(2, np.int32), np.zeros(2, bool), names)
    done = adjust_model(raw, tmp_path / "out.onnx", val, np.ones(len(names)), (0.0,))
    assert done["alpha"] == 0.0 and done["val_miou_by_alpha"] == {"0.0": 100.0}
    assert (tmp_path / "out.onnx").read_bytes() == raw.read_bytes()
