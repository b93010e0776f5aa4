"""``wardmap segment`` on a tiny simulated data set with a tiny ONNX segmentation model."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from procs import wardmap

from wardmap.shared.dataset import DatasetReader

pytest.importorskip("onnx", reason="building test models needs the onnx package (dev dependency)")

HELPER = Path(__file__).resolve().parents[1] / "server" / "perception" / "tiny_onnx.py"



def write_tiny_seg(path: Path, **kwargs: object) -> Path:
    spec = importlib.util.spec_from_file_location("tiny_onnx", HELPER)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.write_tiny_seg(path, **kwargs)  # type: ignore[no-any-return]


@pytest.fixture(scope="module")
def sim_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("segcli") / "aisle"
    p = wardmap("sim", "--scenario", "aisle_slow_1", "--seed", "1000", "--out", str(root), "--frames", "3")
    assert p.returncode == 0, p.stderr
    return root


def test_segment_writes_one_class_png_per_frame(sim_data: Path, tmp_path: Path) -> None:
    """Every rgb stamp gets DIR/<stamp>.png with the tiny model's classes; classes.json names them."""
    model = write_tiny_seg(tmp_path / "tiny.onnx", input_wh=(64, 48))
    out = tmp_path / "seg"
    p = wardmap("segment", str(sim_data), "--model", str(model), "--out", str(out))
    assert p.returncode == 0, p.stderr
    summary = json.loads(p.stdout.strip().splitlines()[-1])
    assert summary["frames"] == 3
    classes = json.loads((out / "classes.json").read_text())
    assert classes["0"] == "background" and classes["1"] == "person" and len(classes) == 14
    reader = DatasetReader(sim_data)
    written = sorted(f.name for f in out.glob("*.png"))
    assert written == sorted(f"{s:.6f}.png" for s in reader.stamps)
    assert all((sim_data / "rgb" / name).is_file() for name in written)  # same naming as the rgb images
    for i, name in enumerate(sorted(written)):
        classes_img = cv2.imread(str(out / name), cv2.IMREAD_UNCHANGED)
        assert classes_img.dtype == np.uint8 and classes_img.shape == (480, 640)
        # The tiny model: "red" (R > 0.5 of 1) -> person, "green" -> door, else background.
        rgb = reader.frame(i).rgb
        small = cv2.resize(rgb, (64, 48), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
        logits = np.stack([np.zeros_like(small[..., 0]), 10 * small[..., 0] - 5, 10 * small[..., 1] - 5])
        expect = np.array([0, 1, 9])[np.argmax(logits, axis=0)]
        # Each model pixel covers 10 x 10 image pixels. Class boundaries are refined from the
        # bilinear logits (SegContract.decode), so compare model pixels away from a boundary,
        # whose whole block keeps their class.
        kernel = np.ones((3, 3), np.uint8)
        inner = cv2.erode(expect.astype(np.uint8), kernel) == cv2.dilate(expect.astype(np.uint8), kernel)
        blocks = np.kron(inner, np.ones((10, 10), bool))
        assert inner.mean() > 0.5
        assert np.mean(classes_img[blocks] == np.kron(expect, np.ones((10, 10), int))[blocks]) > 0.999
        assert len(np.unique(classes_img[blocks])) >= 2  # the check is not all background


def test_segment_bad_input_gives_one_line(sim_data: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    for args, needle in (
        (["--model", str(bad)], "not a readable ONNX model"),
        (["--model", f"yolox:{tmp_path / 'missing.onnx'}"], "model file not found"),
        (["--model", str(bad), "--max-frames", "0"], "--max-frames must be positive"),
    ):
        p = wardmap("segment", str(sim_data), "--out", str(tmp_path / "o"), *args)
        assert p.returncode == 1 and "Traceback" not in p.stderr, p.stderr
        lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and needle in lines[0], p.stderr
    p = wardmap("segment", str(tmp_path / "nope"), "--model", str(bad), "--out", str(tmp_path / "o"))
    assert p.returncode == 1 and "Traceback" not in p.stderr
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    p = wardmap("segment", str(sim_data), "--model", str(bad), "--out", str(tmp_path / "full"))
    assert p.returncode == 1 and "not empty" in p.stderr
