"""Segmentation training: BAFF (paper 003 Eq. 2), the network, and a 2-step train + ONNX export smoke run."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from wardmap.shared.knowledge import KnowledgeGraph  # noqa: E402
from wardmap.tools.training.segdata import SegDataConfig, TrainSegConfig  # noqa: E402
from wardmap.tools.training.training import (  # noqa: E402
    Baff,
    BaffSkipNet,
    train_and_export,
)


@pytest.mark.parametrize("size", [(30, 40), (15, 20), (17, 23)])
def test_baff_shapes_and_convex_blend(size: tuple[int, int]) -> None:
    """BAFF keeps (N, l, K, L), including sizes that are not multiples of the block; its
    weights lie in (0, 1); fusing a map with itself returns it (convex blend, Eq. 2 last line);
    the output lies between the two inputs element-wise."""
    torch.manual_seed(0)
    baff = Baff(8, 4)
    z_a = torch.randn(2, 8, *size)
    z_b = torch.randn(2, 8, *size)
    with torch.no_grad():
        out = baff(z_a, z_b)
        h5 = baff.weights(z_a, z_b)
    assert out.shape == z_a.shape
    assert h5.shape == z_a.shape and float(h5.min()) > 0 and float(h5.max()) < 1
    with torch.no_grad():
        torch.testing.assert_close(baff(z_a, z_a), z_a)
    lo, hi = torch.minimum(z_a, z_b), torch.maximum(z_a, z_b)
    assert bool(((out >= lo - 1e-6) & (out <= hi + 1e-6)).all())


def test_baff_weights_are_blockwise() -> None:
    """Inside one block the weight varies only by bilinear interpolation between block centres:
    with the 3x3 conv zeroed and a 1-block map, every pixel gets the same weight per channel."""
    baff = Baff(3, 4)
    with torch.no_grad():
        baff.w4.weight.zero_()
        baff.w4.bias.fill_(0.7)
    h5 = baff.weights(torch.randn(1, 3, 4, 4), torch.randn(1, 3, 4, 4))
    torch.testing.assert_close(h5, torch.full_like(h5, float(torch.sigmoid(torch.tensor(0.7)))))


def test_baff_rejects_mismatched_inputs() -> None:
    with pytest.raises(ValueError, match="BAFF inputs must match"):
        Baff(4, 2)(torch.zeros(1, 4, 8, 8), torch.zeros(1, 4, 8, 6))


def test_network_logits_at_input_resolution() -> None:
    """The network returns (N, C, H, W) logits at the input size, also for training crops."""
    net = BaffSkipNet(TrainSegConfig(), 14).eval()
    with torch.no_grad():
        assert net(torch.rand(1, 3, 240, 320)).shape == (1, 14, 240, 320)
        assert net(torch.rand(2, 3, 192, 256)).shape == (2, 14, 192, 256)
        rgbd = BaffSkipNet(TrainSegConfig(depth_input=True), 14).eval()
        assert rgbd(torch.rand(1, 4, 240, 320)).shape == (1, 14, 240, 320)


def _tiny_cfg(tmp_path: Path, **kw: object) -> TrainSegConfig:
    base: dict[str, object] = dict(
        threads=1,
        cache_dir=str(tmp_path / "cache"),
        data=SegDataConfig(scenarios=("walking_staff",), seeds=(1,), frames_per_world=4),
        val=SegDataConfig(scenarios=("ward_chairs",), seeds=(1001,), frames_per_world=1),
        epochs=3,
        batch_size=2,
        crop=(96, 128),
        depth_input=True,
        device="cpu",
    )
    base.update(kw)
    return TrainSegConfig(**base)  # type: ignore[arg-type]


@pytest.mark.parametrize("depth_input", [False, True], ids=["rgb", "rgbd"])
def test_two_step_training_exports_contract_onnx(tmp_path: Path, depth_input: bool) -> None:
    """Two optimiser steps on a few tiny samples export one ONNX file that meets the contract
    (names, shapes, metadata, self-contained) and matches torch; the model card is written.
    An RGB-D network takes a 4-channel input."""
    import onnxruntime as ort

    cfg = _tiny_cfg(
        tmp_path,
        data=SegDataConfig(scenarios=("walking_staff",), seeds=(1,), frames_per_world=2),
        epochs=1,
        max_steps=2,
        depth_input=depth_input,
        device="auto",
    )
    out = tmp_path / "model" / "seg.onnx"
    result = train_and_export(cfg, out, command="pytest smoke")
    names = ["background", *KnowledgeGraph.load().names]

    assert sorted(p.name for p in out.parent.iterdir()) == ["seg.md", "seg.onnx"]  # no external data
    model = onnx.load(str(out))
    onnx.checker.check_model(model)
    meta = {p.key: p.value for p in model.metadata_props}
    assert json.loads(meta["wardmap.classes"]) == names
    assert meta["wardmap.input_size"] == "320x240"

    sess = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    (inp,), (outp,) = sess.get_inputs(), sess.get_outputs()
    channels = 4 if depth_input else 3
    assert (inp.name, inp.shape, inp.type) == ("image", [1, channels, 240, 320], "tensor(float)")
    assert (outp.name, outp.shape, outp.type) == ("logits", [1, len(names), 240, 320], "tensor(float)")
    x = np.random.default_rng(0).random((1, channels, 240, 320), np.float32)
    logits = sess.run(["logits"], {"image": x})[0]
    assert logits.shape == (1, 14, 240, 320) and np.isfinite(logits).all()

    assert result.summary["onnx_torch_max_abs_diff"] < 1e-3
    assert result.summary["train_frames"] == 2 and result.summary["val_frames"] == 1
    assert set(result.metrics["per_class_iou"]) == set(names)
    card = out.with_suffix(".md").read_text()
    assert "pytest smoke" in card and "mIoU" in card and "seeds >= 1000" in card


def test_bad_output_path_is_a_clear_error(tmp_path: Path) -> None:
    from wardmap.tools.training.segdata import TrainingError

    with pytest.raises(TrainingError, match=r"must end in \.onnx"):
        train_and_export(TrainSegConfig(), tmp_path / "model.pt")


def test_one_cycle_matches_torch_one_cycle_lr() -> None:
    """The clock-driven schedule follows torch's OneCycleLR (cosine, defaults) step for step."""
    from wardmap.tools.training.training import one_cycle

    p = torch.nn.Parameter(torch.zeros(1))
    opt = torch.optim.AdamW([p], lr=0.01)
    total = 50
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=0.01, total_steps=total, pct_start=0.1)
    for step in range(total - 1):
        # OneCycleLR's phases end on step indices (pct * total - 1, total - 1): compare in its units.
        edge = 0.1 * total - 1
        frac = 0.1 * step / edge if step <= edge else 0.1 + 0.9 * (step - edge) / (total - 1 - edge)
        lr, beta1 = one_cycle(frac, 0.01)
        assert lr == pytest.approx(opt.param_groups[0]["lr"], rel=1e-6)
        assert beta1 == pytest.approx(opt.param_groups[0]["betas"][0], rel=1e-6)
        opt.step()
        sched.step()
    assert one_cycle(1.0, 0.01)[0] == pytest.approx(0.01 / 25 / 1e4)


def test_batches_do_not_depend_on_loader_processes(tmp_path: Path) -> None:
    """Each step's batch is seeded by (seed, step): two loader processes give the same batches
    as the training loop alone; repeat-factor sampling draws as many frames per epoch."""
    from wardmap.tools.training.segdata import build_samples
    from wardmap.tools.training.training import _Batches, _plan

    cfg = _tiny_cfg(tmp_path, repeat_factor=0.5)
    samples = build_samples(cfg.data, cfg.cache_dir)
    plan = _plan(cfg, samples)
    assert len(plan) == cfg.epochs * (len(samples) // cfg.batch_size)
    alone = [_Batches(cfg, samples, plan)[i] for i in range(len(plan))]
    loader = torch.utils.data.DataLoader(_Batches(cfg, samples, plan), batch_size=None, num_workers=2)
    for (xa, ya), (xb, yb) in zip(alone, loader, strict=True):
        torch.testing.assert_close(xa, xb)
        torch.testing.assert_close(ya, yb)


def test_time_budget_stops_training_and_best_epoch_is_kept(tmp_path: Path, caplog: pytest.LogCaptureFixture
                                                           ) -> None:
    """A wall-clock budget ends the run before its epochs; with select_best the returned network
    is the epoch with the best validation mIoU (its weights, not the last epoch's)."""
    import logging

    from wardmap.tools.training.segdata import build_samples
    from wardmap.tools.training.training import _val_miou, train_model

    cfg = _tiny_cfg(tmp_path, epochs=500, time_budget_s=4.0, select_best=True)
    train = build_samples(cfg.data, cfg.cache_dir)
    val = build_samples(cfg.val, cfg.cache_dir)
    with caplog.at_level(logging.INFO, logger="wardmap.tools.training.training"):
        model, losses = train_model(cfg, train, val=val)
    assert 1 <= len(losses) < 500
    assert any("time budget" in r.message for r in caplog.records)
    kept = [r.message for r in caplog.records if r.message.startswith("keeping epoch")]
    scores = [float(r.message.split("validation mIoU ")[1].split(" %")[0]) for r in caplog.records
              if r.message.startswith("epoch ")]
    assert kept and f"{max(scores):.1f} %" in kept[0]
    assert _val_miou(model, val, torch.device("cpu"), True) == pytest.approx(max(scores), abs=0.05)


def test_cuda_without_a_gpu_is_a_clear_error(tmp_path: Path) -> None:
    from wardmap.tools.training.segdata import TrainingError, build_samples
    from wardmap.tools.training.training import train_model

    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    cfg = _tiny_cfg(tmp_path, device="cuda")
    with pytest.raises(TrainingError, match="sees no GPU"):
        train_model(cfg, build_samples(cfg.data, cfg.cache_dir))
    with pytest.raises(TrainingError, match="sees no GPU"):  # before any frame is rendered
        train_and_export(replace(cfg, cache_dir=str(tmp_path / "none")), tmp_path / "m.onnx")
    assert not (tmp_path / "none").exists()
