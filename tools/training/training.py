"""Train the hospital segmentation network (paper 003 Sec. IV-B) and export it to ONNX.

The only module of wardmap that imports torch (extra ``train``); nothing imports it at
import time. The server runs the exported file with onnxruntime.

Network (:class:`BaffSkipNet`): input ``[N, 3, H, W]`` RGB in 0..1, or ``[N, 4, H, W]`` RGB
plus depth in metres (0 = no data) with ``depth_input``, normalised inside the model; a
MobileNetV2-style encoder of inverted residual blocks (expansion, depthwise 3x3, linear
projection, residual when the shape allows) at a small width; a skip decoder that
climbs from stride 32 to stride 2, fusing each upsampled deep level with the encoder skip of
the same stride through block-adaptive feature fusion (:class:`Baff`, Eq. 2); logits
``[N, C, H, W]`` at full input resolution (bilinear from stride 2).

ONNX contract (the inference side depends on it, ``wardmap.shared.segmentation``): input
``image`` float32 ``[1, 3, 240, 320]`` RGB 0..1 (``[1, 4, 240, 320]`` RGB-D); output
``logits`` float32 ``[1, C, 240, 320]``, C = 1 + knowledge-graph classes; metadata
``wardmap.classes`` (JSON list of names, ``background`` first) and ``wardmap.input_size``
(``"320x240"``). One self-contained file.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import os
import platform
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812 - torch's conventional alias
from numpy.typing import NDArray
from torch import Tensor, nn

from wardmap.shared.config import to_mapping
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.tools.training.logit_adjust import adjust_model, onnx_logits
from wardmap.tools.training.segdata import (
    IGNORE_INDEX,
    SegSamples,
    TrainingError,
    TrainSegConfig,
    augment,
    build_samples,
    class_names,
    class_weights,
    config_hash,
    confusion,
    iou_from_confusion,
    repeat_factors,
)
from wardmap.tools.training.sitedata import load_site_samples

log = logging.getLogger(__name__)

ONNX_OPSET = 17
# ImageNet statistics: the model normalises its 0..1 RGB input itself. Depth (metres): a
# rough spread of indoor ranges; 0 (no data) maps to about -1.7.
_MEAN = (0.485, 0.456, 0.406)
_STD = (0.229, 0.224, 0.225)
_DEPTH_MEAN_M = 2.5
_DEPTH_STD_M = 1.5

Progress = Callable[[str, int, int, str], None]


# ---- network -----------------------------------------------------------------------------


def _conv_bn(
    cin: int, cout: int, k: int = 3, stride: int = 1, groups: int = 1, act: bool = True
) -> nn.Sequential:
    layers: list[nn.Module] = [
        nn.Conv2d(cin, cout, k, stride, k // 2, groups=groups, bias=False),
        nn.BatchNorm2d(cout),
    ]
    if act:
        layers.append(nn.ReLU6(inplace=True))
    return nn.Sequential(*layers)


class InvertedResidual(nn.Module):
    """MobileNetV2 block: 1x1 expand (ReLU6), 3x3 depthwise (ReLU6), 1x1 linear projection."""

    def __init__(self, cin: int, cout: int, stride: int, expansion: int) -> None:
        super().__init__()
        hidden = cin * expansion
        layers: list[nn.Module] = []
        if expansion != 1:
            layers.append(_conv_bn(cin, hidden, 1))
        layers += [_conv_bn(hidden, hidden, 3, stride, groups=hidden), _conv_bn(hidden, cout, 1, act=False)]
        self.block = nn.Sequential(*layers)
        self.residual = stride == 1 and cin == cout

    def forward(self, x: Tensor) -> Tensor:
        y = self.block(x)
        return x + y if self.residual else y


class Baff(nn.Module):
    """Block-adaptive feature fusion of two feature maps, paper 003 Eq. 2.

    Both inputs have ``l`` channels and the same ``K x L`` size. The map is divided into
    ``block x block`` blocks; per channel ``j`` (depthwise, as Eq. 2 indexes every weight
    by the feature map ``j``)::

        h1 = z_a^j * w1^j + b1^j          (kernel = stride = block: one value per block)
        h2 = z_b^j * w2^j + b2^j
        h3 = mu(h1 + h2)
        h4 = mu(h3 * w4^j + b4^j)         (3x3 over the block grid: the block weight matrix)
        h5 = up(h4)                       (bilinear, back to K x L)
        sigma^j = h5 o z_a^j + (1 - h5) o z_b^j

    ``mu`` is the logistic sigmoid, so ``h5`` is a convex weight in (0, 1). Eq. 2 as printed
    computes ``h2`` from ``z_a`` too, which would make ``h1 + h2`` a single convolution of
    ``z_a`` and leave the weights blind to ``z_b``; we read it as ``z_b``, the second layer
    the text introduces. Sizes that are not multiples of ``block`` are padded (replicate)
    for the block convolutions only.

    Args (forward):
        z_a: (N, l, K, L) shallow feature map (the encoder skip).
        z_b: (N, l, K, L) deep feature map (upsampled decoder level).

    Returns:
        sigma: (N, l, K, L).
    """

    def __init__(self, channels: int, block: int) -> None:
        super().__init__()
        self.block = block
        self.w1 = nn.Conv2d(channels, channels, block, block, groups=channels)
        self.w2 = nn.Conv2d(channels, channels, block, block, groups=channels)
        self.w4 = nn.Conv2d(channels, channels, 3, 1, 1, groups=channels)

    def weights(self, z_a: Tensor, z_b: Tensor) -> Tensor:
        """``h5``: the per-pixel, per-channel fusion weight of ``z_a`` (N, l, K, L) in (0, 1)."""
        k, l_ = z_a.shape[-2:]
        pad_h, pad_w = (-k) % self.block, (-l_) % self.block
        if pad_h or pad_w:
            z_a_p = F.pad(z_a, (0, pad_w, 0, pad_h), mode="replicate")
            z_b_p = F.pad(z_b, (0, pad_w, 0, pad_h), mode="replicate")
        else:
            z_a_p, z_b_p = z_a, z_b
        h3 = torch.sigmoid(self.w1(z_a_p) + self.w2(z_b_p))
        h4 = torch.sigmoid(self.w4(h3))
        if h4.shape[-2:] == (k, l_):
            return h4
        return F.interpolate(h4, size=(int(k), int(l_)), mode="bilinear", align_corners=False)

    def forward(self, z_a: Tensor, z_b: Tensor) -> Tensor:
        if z_a.shape != z_b.shape:
            raise ValueError(f"BAFF inputs must match, got {tuple(z_a.shape)} and {tuple(z_b.shape)}")
        h5 = self.weights(z_a, z_b)
        return h5 * z_a + (1.0 - h5) * z_b


class _DecoderLevel(nn.Module):
    """Upsample the deeper level, project both to ``channels``, fuse by BAFF, refine."""

    def __init__(self, deep: int, skip: int, channels: int, block: int) -> None:
        super().__init__()
        self.proj_deep = _conv_bn(deep, channels, 1)
        self.proj_skip = _conv_bn(skip, channels, 1)
        self.baff = Baff(channels, block)
        self.refine = nn.Sequential(
            _conv_bn(channels, channels, 3, groups=channels), _conv_bn(channels, channels, 1)
        )

    def forward(self, deep: Tensor, skip: Tensor) -> Tensor:
        up = F.interpolate(self.proj_deep(deep), size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return self.refine(self.baff(self.proj_skip(skip), up))


class BaffSkipNet(nn.Module):
    """MobileNetV2-style encoder + BAFF skip decoder (paper 003 Fig. 5), see the module docstring.

    Input (N, 3, H, W) RGB 0..1, or (N, 4, H, W) RGB 0..1 + depth metres with
    ``cfg.depth_input``; output logits (N, num_classes, H, W).
    """

    mean: Tensor
    std: Tensor

    def __init__(self, cfg: TrainSegConfig, num_classes: int) -> None:
        super().__init__()
        mean, std = (*_MEAN, _DEPTH_MEAN_M), (*_STD, _DEPTH_STD_M)
        self.in_channels = 4 if cfg.depth_input else 3
        self.register_buffer("mean", torch.tensor(mean[: self.in_channels]).view(1, -1, 1, 1))
        self.register_buffer("std", torch.tensor(std[: self.in_channels]).view(1, -1, 1, 1))
        self.stem = _conv_bn(self.in_channels, cfg.stem_channels, 3, 2)
        stages: list[nn.Module] = []
        cin = cfg.stem_channels
        strides, stride = [], 2
        channels = []
        for t, c, n, s in cfg.encoder:
            blocks = [InvertedResidual(cin if i == 0 else c, c, s if i == 0 else 1, t) for i in range(n)]
            stages.append(nn.Sequential(*blocks))
            cin = c
            stride *= s
            strides.append(stride)
            channels.append(c)
        self.stages = nn.ModuleList(stages)
        self.skip_stages = tuple(cfg.skip_stages)
        skips = list(self.skip_stages)
        levels: list[nn.Module] = []
        deep = channels[skips[-1]]
        for out_c, si in zip(cfg.decoder_channels, reversed(skips[:-1]), strict=True):
            block = max(1, cfg.baff_block_px // strides[si])
            levels.append(_DecoderLevel(deep, channels[si], out_c, block))
            deep = out_c
        self.levels = nn.ModuleList(levels)
        self.head = nn.Conv2d(deep, num_classes, 1)

    def forward(self, image: Tensor) -> Tensor:
        x = self.stem((image - self.mean) / self.std)
        feats: list[Tensor] = []
        for stage in self.stages:
            x = stage(x)
            feats.append(x)
        skips = [feats[i] for i in self.skip_stages]
        y = skips[-1]
        for level, skip in zip(self.levels, reversed(skips[:-1]), strict=True):
            y = level(y, skip)
        return F.interpolate(self.head(y), size=image.shape[-2:], mode="bilinear", align_corners=False)


# ---- training ----------------------------------------------------------------------------


@dataclass(frozen=True)
class TrainResult:
    """What :func:`train_and_export` produced.

    Attributes:
        onnx_path: the exported model.
        card_path: the model card (Markdown) beside it.
        metrics: validation metrics (``miou``, ``per_class_iou``, ...).
        summary: everything the model card states, JSON-ready.
    """

    onnx_path: Path
    card_path: Path
    metrics: dict[str, Any]
    summary: dict[str, Any]


def _device(cfg: TrainSegConfig) -> torch.device:
    """The training device of ``cfg.device`` (``auto``: CUDA when torch sees a GPU)."""
    cuda = torch.cuda.is_available()
    if cfg.device == "cuda" and not cuda:
        raise TrainingError("device = cuda, but torch sees no GPU (torch.cuda.is_available() is False)")
    return torch.device("cuda" if cuda and cfg.device != "cpu" else "cpu")


def _plan(cfg: TrainSegConfig, samples: SegSamples) -> list[NDArray[np.int64]]:
    """Sample indices of every optimiser step, all epochs: a permutation per epoch, or with
    ``repeat_factor`` as many frames drawn (with replacement) in proportion to their repeat
    factors (:func:`repeat_factors`)."""
    rng = np.random.default_rng([cfg.seed, 1])
    n, b = len(samples), cfg.batch_size
    p = None
    if cfg.repeat_factor > 0:
        r = repeat_factors(samples.classes, len(samples.names), cfg.repeat_factor)
        p = r / r.sum()
    steps: list[NDArray[np.int64]] = []
    for _ in range(cfg.epochs):
        order = rng.permutation(n) if p is None else rng.choice(n, size=n, p=p)
        steps += [order[i : i + b] for i in range(0, n - b + 1, b)]
    return steps[: cfg.max_steps] if cfg.max_steps else steps


class _Batches(torch.utils.data.Dataset[tuple[Tensor, Tensor]]):
    """Item ``step`` = the augmented batch of that step: ``x`` (B, 3|4, h, w) float32 (RGB
    0..1, depth metres), ``y`` (B, h, w) int64 class indices. Augmentation is seeded by
    ``(seed, step)``, so batches do not depend on the number of loader processes."""

    def __init__(self, cfg: TrainSegConfig, samples: SegSamples, plan: list[NDArray[np.int64]]) -> None:
        self.cfg, self.samples, self.plan = cfg, samples, plan

    def __len__(self) -> int:
        return len(self.plan)

    def __getitem__(self, step: int) -> tuple[Tensor, Tensor]:
        cfg, s = self.cfg, self.samples
        rng = np.random.default_rng([cfg.seed, 2, step])
        pairs = [
            augment(s.rgb[i], s.classes[i], rng, cfg.crop, s.depth[i] if cfg.depth_input else None)
            for i in self.plan[step]
        ]
        x = torch.from_numpy(np.stack([p[0] for p in pairs])).permute(0, 3, 1, 2).float().div_(255.0)
        if cfg.depth_input:
            d = torch.from_numpy(np.stack([cast(NDArray[np.float32], p[2]) for p in pairs]))
            x = torch.cat([x, d[:, None]], dim=1)
        y = torch.from_numpy(np.stack([p[1] for p in pairs]).astype(np.int64))
        return x, y


def _load_weights(model: BaffSkipNet, path: Path) -> bool:
    """Start ``model`` from ``path`` (``init_weights``): a torch state dict (``MODEL.pt``), or an
    exported ``MODEL.onnx`` (:func:`_weights_from_onnx`). Returns True for an ONNX file, whose
    batch norms must stay frozen while training (their statistics are folded away).

    Raises:
        TrainingError: a missing or unreadable file, or weights of another network shape.
    """
    if not path.is_file():
        raise TrainingError(f"init_weights: {path} not found")
    if path.suffix == ".onnx":
        _weights_from_onnx(model, path)
        log.info("starting from the weights in %s (batch norms frozen)", path)
        return True
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        model.load_state_dict(state)
    except (OSError, RuntimeError, ValueError, KeyError, TypeError, AttributeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise TrainingError(f"init_weights: {path} does not fit this network (encoder, decoder, depth "
                            f"input, classes): {first}") from exc
    log.info("starting from the weights in %s", path)
    return False


def _weights_from_onnx(model: BaffSkipNet, path: Path) -> None:
    """Load the weights of an exported model (the packaged ``hospital_seg.onnx``) into ``model``.

    The exporter folds each batch norm into the convolution before it (``onnx::Conv_*``
    initializers, in execution order); other parameters keep their names. A folded pair goes back
    as the convolution's weight and a batch norm that only adds the folded bias (scale 1, mean 0,
    variance 1 - eps), so the network computes what the file does as long as its batch norms stay
    in eval mode. The logit adjustment of the file (``logit_bias``) is left out: the export adds
    a new one. Checked: torch and onnxruntime logits agree within 1e-3 on a random input.

    Raises:
        TrainingError: onnx missing, or a file whose layers or shapes are not this network's.
    """
    try:
        import onnx
        import onnxruntime as ort
        from onnx import numpy_helper
    except ImportError as exc:
        raise TrainingError("init_weights from an .onnx file needs onnx: pip install -e '.[train]'") from exc
    where = f"init_weights: {path}"
    try:
        proto = onnx.load(str(path))
    except Exception as exc:  # onnx raises its own untyped errors for unreadable files
        raise TrainingError(f"{where}: not a readable ONNX model ({type(exc).__name__})") from exc
    init = {i.name: numpy_helper.to_array(i) for i in proto.graph.initializer}
    state = model.state_dict()
    pairs: dict[nn.Module, nn.BatchNorm2d] = {}
    for module in model.modules():
        kids = list(module.children()) if isinstance(module, nn.Sequential) else []
        for conv, bn in itertools.pairwise(kids):
            if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                pairs[conv] = bn
    order: list[nn.Module] = []
    hooks = [conv.register_forward_hook(lambda m, _i, _o: order.append(m)) for conv in pairs]
    height, width = 240, 320
    try:
        with torch.no_grad():
            model.eval()(torch.zeros(1, model.in_channels, height, width))
    finally:
        for hook in hooks:
            hook.remove()
    folded = [n for n in proto.graph.node if n.op_type == "Conv" and n.input[1] not in state]
    if len(folded) != len(order):
        raise TrainingError(f"{where}: {len(folded)} folded convolutions, this network has {len(order)}; "
                            "is it a model of this config (encoder, decoder)?")
    with torch.no_grad():
        for node, conv in zip(folded, order, strict=True):
            weight = init.get(node.input[1])
            bias = init.get(node.input[2]) if len(node.input) > 2 else None
            target = cast(nn.Conv2d, conv).weight
            if weight is None or tuple(weight.shape) != tuple(target.shape):
                found = None if weight is None else weight.shape
                raise TrainingError(f"{where}: convolution {node.name} has weights {found}, "
                                    f"expected {tuple(target.shape)}")
            bn = pairs[conv]
            target.copy_(torch.from_numpy(np.array(weight)))
            bn.weight.fill_(1.0)
            bn.bias.copy_(torch.from_numpy(np.array(bias)) if bias is not None else torch.zeros_like(bn.bias))
            if bn.running_mean is None or bn.running_var is None:  # _conv_bn tracks statistics
                raise TrainingError(f"{where}: a batch norm of this network keeps no running statistics")
            bn.running_mean.zero_()
            bn.running_var.fill_(1.0 - bn.eps)
        in_pairs = set(pairs) | set(pairs.values())
        folded_names = {f"{name}.{p}" for name, m in model.named_modules() if m in in_pairs
                        for p in ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")}
        missing = [k for k in state if k not in folded_names and k not in init]
        if missing:
            raise TrainingError(f"{where}: no weights for {', '.join(missing[:4])}; is it a model of this "
                                "config?")
        for key, value in state.items():
            if key in init and key not in folded_names:
                if tuple(init[key].shape) != tuple(value.shape):
                    raise TrainingError(f"{where}: {key} is {init[key].shape}, expected {tuple(value.shape)}")
                value.copy_(torch.from_numpy(np.array(init[key])))
    x = torch.rand(1, model.in_channels, height, width, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        ours = model(x).numpy()
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    theirs = session.run(None, {session.get_inputs()[0].name: x.numpy()})[0]
    theirs = theirs - init.get("logit_bias", np.zeros(1, np.float32))
    if ours.shape != theirs.shape or not float(np.abs(ours - theirs).max()) < 1e-3:
        raise TrainingError(f"{where}: the weights read back do not reproduce the file's logits")


def _set_train(model: nn.Module, frozen_batchnorm: bool) -> None:
    """Training mode; with ``frozen_batchnorm`` the batch norms stay in eval mode (their running
    statistics are used and kept; their scale and shift still learn)."""
    model.train()
    if frozen_batchnorm:
        for module in model.modules():
            if isinstance(module, nn.BatchNorm2d):
                module.eval()


def one_cycle(progress: float, max_lr: float, pct_start: float = 0.1) -> tuple[float, float]:
    """``(learning rate, Adam beta1)`` at ``progress`` in [0, 1] of a one-cycle schedule (Smith
    2018; torch's ``OneCycleLR`` defaults: cosine phases, start ``max_lr / 25``, end 1e-4 of
    that, beta1 0.95 -> 0.85 -> 0.95)."""
    lo, end = max_lr / 25.0, max_lr / 25.0 / 1e4
    p = min(max(progress, 0.0), 1.0)
    if p < pct_start:
        a = (1.0 - math.cos(math.pi * p / pct_start)) / 2.0
        return lo + (max_lr - lo) * a, 0.95 - 0.10 * a
    a = (1.0 - math.cos(math.pi * (p - pct_start) / (1.0 - pct_start))) / 2.0
    return max_lr + (end - max_lr) * a, 0.85 + 0.10 * a


def _val_miou(model: BaffSkipNet, val: SegSamples, device: torch.device, depth: bool) -> float:
    """Validation mIoU % of the network's own argmax (no logit adjustment), computed in torch;
    leaves the model in eval mode."""
    n = len(val.names)
    cm = torch.zeros(n * n, dtype=torch.int64, device=device)
    model.eval()
    with torch.no_grad():
        for i in range(0, len(val), 16):
            x = torch.from_numpy(val.rgb[i : i + 16]).to(device).permute(0, 3, 1, 2).float().div_(255.0)
            if depth:
                d = torch.from_numpy(val.depth[i : i + 16].astype(np.float32)).to(device) / 1000.0
                x = torch.cat([x, d[:, None]], dim=1)
            pred = model(x).argmax(1).reshape(-1)
            t = torch.from_numpy(val.classes[i : i + 16]).to(device).reshape(-1).long()
            keep = t < n
            cm += torch.bincount(t[keep] * n + pred[keep], minlength=n * n)
    iou = iou_from_confusion(cm.reshape(n, n).cpu().numpy())
    present = cm.reshape(n, n).sum(1).cpu().numpy() > 0
    return float(np.mean(iou[present]) * 100.0)


def train_model(
    cfg: TrainSegConfig,
    samples: SegSamples,
    progress: Progress | None = None,
    val: SegSamples | None = None,
) -> tuple[BaffSkipNet, list[float]]:
    """Train a :class:`BaffSkipNet` on ``samples``; returns it (eval mode, on the CPU) and the
    per-epoch mean loss.

    On the CPU, deterministic for a given config and samples (seeded torch, sample order,
    augmentation) unless ``time_budget_s`` stops it. With ``select_best`` the epoch with the
    best mIoU on ``val`` is returned.
    """
    if len(samples) < cfg.batch_size:
        raise TrainingError(f"{len(samples)} samples are fewer than one batch of {cfg.batch_size}")
    if cfg.select_best and val is None:
        raise TrainingError("select_best needs validation samples")
    device = _device(cfg)
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    # CUDA's deterministic kernels (interpolation backward) are slow or missing; a GPU run is
    # not bit-reproducible, a CPU run is.
    torch.use_deterministic_algorithms(device.type == "cpu", warn_only=True)
    torch.backends.cudnn.benchmark = device.type == "cuda"
    num_classes = len(samples.names)
    model = BaffSkipNet(cfg, num_classes)
    frozen_batchnorm = _load_weights(model, Path(cfg.init_weights)) if cfg.init_weights else False
    layout = torch.channels_last if cfg.channels_last else torch.contiguous_format
    model = cast(Any, model).to(device=device, memory_format=layout)
    weights = torch.from_numpy(
        class_weights(samples.classes, num_classes, cfg.class_weight_power, cfg.max_class_weight)
    )
    loss_fn = nn.CrossEntropyLoss(weight=weights.to(device), ignore_index=IGNORE_INDEX)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    plan = _plan(cfg, samples)
    steps_per_epoch = len(samples) // cfg.batch_size
    total = len(plan)
    loader = torch.utils.data.DataLoader(
        _Batches(cfg, samples, plan),
        batch_size=None,
        num_workers=cfg.loader_workers,
        pin_memory=device.type == "cuda",
        prefetch_factor=4 if cfg.loader_workers else None,
    )
    _set_train(model, frozen_batchnorm)
    losses: list[float] = []
    best: tuple[float, dict[str, Tensor] | None, int] = (-1.0, None, 0)
    epoch_loss, n_batches, epoch = 0.0, 0, 0
    started = time.perf_counter()

    def end_epoch() -> None:
        nonlocal epoch_loss, n_batches, best
        losses.append(epoch_loss / max(n_batches, 1))
        note = ""
        if cfg.select_best and val is not None:
            miou = _val_miou(model, val, device, cfg.depth_input)
            _set_train(model, frozen_batchnorm)
            note = f", validation mIoU {miou:.1f} %"
            if miou > best[0]:
                best = (miou, {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}, epoch + 1)
        log.info("epoch %d: mean loss %.4f (%.0f s)%s", epoch + 1, losses[-1], time.perf_counter() - started,
                 note)
        epoch_loss, n_batches = 0.0, 0

    for step, (xb, yb) in enumerate(loader):
        elapsed = time.perf_counter() - started
        frac = step / total
        if cfg.time_budget_s:
            frac = max(frac, elapsed / cfg.time_budget_s)
        if frac >= 1.0:
            log.info("time budget %.0f s reached after %d of %d steps", cfg.time_budget_s, step, total)
            break
        lr, beta1 = one_cycle(frac, cfg.lr)
        for group in opt.param_groups:
            group["lr"], group["betas"] = lr, (beta1, group["betas"][1])
        x = xb.to(device, non_blocking=True).contiguous(memory_format=layout)
        y = yb.to(device, non_blocking=True)
        loss = loss_fn(model(x), y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        value = float(loss.detach())
        epoch_loss += value
        n_batches += 1
        if progress is not None:
            progress("train", step + 1, total, f"epoch {epoch + 1} loss {value:.3f} {elapsed:.0f} s")
        if (step + 1) % steps_per_epoch == 0:
            end_epoch()
            epoch += 1
    if n_batches:
        end_epoch()
    if best[1] is not None:
        log.info("keeping epoch %d (validation mIoU %.1f %%)", best[2], best[0])
        model.load_state_dict(best[1])
    model = cast(Any, model).to(device="cpu", memory_format=torch.contiguous_format)
    model.eval()
    return model, losses


# ---- export and validation ---------------------------------------------------------------


def export_onnx(model: BaffSkipNet, path: Path, names: Sequence[str], width: int, height: int) -> None:
    """Write ``model`` as one self-contained ONNX file with the contract of the module docstring.

    Raises:
        TrainingError: onnx is missing or the export fails.
    """
    try:
        import onnx
    except ImportError as exc:
        raise TrainingError("onnx is not installed; pip install -e '.[train]'") from exc
    model = model.eval()
    dummy = torch.rand(1, model.in_channels, height, width)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.onnx")
    with torch.no_grad(), warnings.catch_warnings():
        # The tracer warns about Python-level shape checks; shapes are fixed in the contract.
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model,
            (dummy,),
            str(tmp),
            input_names=["image"],
            output_names=["logits"],
            opset_version=ONNX_OPSET,
            dynamo=False,
            do_constant_folding=True,
        )
    proto = onnx.load(str(tmp))
    for key, value in (
        ("wardmap.classes", json.dumps(list(names))),
        ("wardmap.input_size", f"{width}x{height}"),
    ):
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(proto)
    onnx.save(proto, str(path))
    tmp.unlink()


def evaluate_onnx(path: Path, samples: SegSamples, threads: int = 1) -> dict[str, Any]:
    """mIoU and per-class IoU of the ONNX model on ``samples`` (numpy on onnxruntime outputs).

    Returns a dict: ``miou`` (mean over classes present in the truth, %), ``per_class_iou``
    ({name: % or None}), ``pixel_accuracy`` (%), ``frames``, ``ms_per_frame`` (mean
    onnxruntime time per frame at ``threads``).
    """
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    n = len(samples.names)
    cm = np.zeros((n, n), np.int64)
    times = []
    for i in range(len(samples)):
        t0 = time.perf_counter()
        logits = onnx_logits(sess, samples.rgb[i], samples.depth[i])
        times.append(time.perf_counter() - t0)
        cm += confusion(logits[0].argmax(0), samples.classes[i], n)
    iou = iou_from_confusion(cm)
    present = cm.sum(1) > 0
    return {
        "miou": float(np.mean(iou[present]) * 100.0),
        "per_class_iou": {
            name: (round(float(iou[k]) * 100.0, 1) if present[k] else None)
            for k, name in enumerate(samples.names)
        },
        "pixel_accuracy": float(np.trace(cm) / max(cm.sum(), 1) * 100.0),
        "frames": len(samples),
        "ms_per_frame": float(np.median(times) * 1000.0),
    }


def check_export(
    model: BaffSkipNet, path: Path, rgb: NDArray[np.uint8], depth_mm: NDArray[np.uint16]
) -> float:
    """Max abs logit difference between torch and onnxruntime on one (H, W, 3) uint8 image
    and its (H, W) uint16 depth in millimetres (used by RGB-D models)."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255.0
    if model.in_channels == 4:
        x = torch.cat([x, torch.from_numpy(depth_mm.astype(np.float32) / 1000.0)[None, None]], dim=1)
    with torch.no_grad():
        ref = model(x).numpy()
    return float(np.abs(onnx_logits(sess, rgb, depth_mm) - ref).max())


def train_and_export(
    cfg: TrainSegConfig,
    out: str | Path,
    *,
    command: str = "",
    progress: Progress | None = None,
    card: bool = True,
) -> TrainResult:
    """Generate (or load cached) samples, train, export ``out`` (ONNX), validate, write the card.

    Args:
        out: ONNX path; the model card is written beside it with the suffix ``.md``.
        command: the command line that made the model (for the card).

    Raises:
        TrainingError: bad output path, too few samples, export failure.
    """
    out = Path(out)
    if out.suffix != ".onnx":
        raise TrainingError(f"--out must end in .onnx, got {out}")
    if out.exists() and not out.is_file():
        raise TrainingError(f"--out {out} exists and is not a file")
    _device(cfg)  # a missing GPU fails before the frames are rendered
    if cfg.init_weights and not Path(cfg.init_weights).is_file():
        raise TrainingError(f"init_weights: {cfg.init_weights} not found")
    started = time.perf_counter()
    kg = KnowledgeGraph.load()
    names = class_names(kg)

    def data_progress(tag: str) -> Callable[[int, int], None]:
        return lambda i, n: progress(tag, i, n, "worlds") if progress is not None else None

    site = load_site_samples(cfg.site, names, cfg.data.width, cfg.data.height)  # bad site data fails first
    train = build_samples(cfg.data, cfg.cache_dir, data_progress("data"), kg, workers=cfg.threads)
    if site is not None:
        train = train.plus(site)
    val = build_samples(cfg.val, cfg.cache_dir, data_progress("val data"), kg, workers=cfg.threads)
    t_data = time.perf_counter() - started
    model, losses = train_model(cfg, train, progress, val)
    t_train = time.perf_counter() - started - t_data
    export_onnx(model, out, names, cfg.data.width, cfg.data.height)
    if cfg.save_weights:
        torch.save(model.state_dict(), out.with_suffix(".pt"))
    diff = check_export(model, out, val.rgb[0], val.depth[0])
    if not math.isfinite(diff) or diff > 1e-2:
        raise TrainingError(f"exported model disagrees with torch: max abs logit difference {diff:.3g}")
    weights = class_weights(train.classes, len(names), cfg.class_weight_power, cfg.max_class_weight)
    adjust = adjust_model(out, out, val, weights, cfg.logit_adjust, threads=cfg.threads)
    metrics = evaluate_onnx(out, val, threads=1)
    if val.on_track.any():
        metrics["on_track"] = evaluate_onnx(out, val.subset(val.on_track), threads=1)
    wall = time.perf_counter() - started
    n_params = sum(p.numel() for p in model.parameters())
    summary: dict[str, Any] = {
        "command": command,
        "wall_time_s": round(wall, 1),
        "data_time_s": round(t_data, 1),
        "data_cached": bool(train.cached and val.cached),
        "data_generation_s": round(train.generation_s + val.generation_s, 1),
        "train_time_s": round(t_train, 1),
        "train_frames": len(train),
        "site_frames": 0 if site is None else len(site),
        "val_frames": len(val),
        "train_data_hash": config_hash(cfg.data),
        "val_data_hash": config_hash(cfg.val),
        "epoch_losses": [round(v, 4) for v in losses],
        "parameters": int(n_params),
        "onnx_bytes": out.stat().st_size,
        "onnx_torch_max_abs_diff": diff,
        "torch": torch.__version__,
        "cpu": platform.processor() or platform.machine(),
        "cpu_cores": os.cpu_count(),
        "device": torch.cuda.get_device_name() if _device(cfg).type == "cuda" else "CPU",
        "epochs_run": len(losses),
        "config": to_mapping(cfg),
        "classes": list(names),
        "class_pixel_share": _class_share(train, names),
        "logit_adjust": adjust,
    }
    card_path = out.with_suffix(".md")
    if card:
        card_path.write_text(model_card(summary, metrics))
    # Kept beside the data cache so a card can be re-rendered without retraining.
    record = Path(cfg.cache_dir) / f"run-{out.stem}.json"
    record.parent.mkdir(parents=True, exist_ok=True)
    record.write_text(json.dumps({"summary": summary, "metrics": metrics}, indent=2) + "\n")
    log.info("validation mIoU %.1f %% on %d frames", metrics["miou"], len(val))
    return TrainResult(out, card_path, metrics, summary)


def _class_share(samples: SegSamples, names: Sequence[str]) -> dict[str, float]:
    counts = np.bincount(samples.classes.reshape(-1), minlength=len(names))[: len(names)]
    return {
        n: round(float(c) / max(int(counts.sum()), 1) * 100.0, 3) for n, c in zip(names, counts, strict=True)
    }


def _track_line(metrics: dict[str, Any]) -> str:
    t = metrics.get("on_track")
    if not t:
        return ""
    person = t["per_class_iou"].get("person")
    person_s = "-" if person is None else f"{person:.1f} %"
    return (
        f"- the {t['frames']} of these frames on the scenarios' own robot trajectories (the view a "
        f"robot has): mIoU {t['miou']:.1f} %, person IoU {person_s}, pixel accuracy "
        f"{t['pixel_accuracy']:.1f} %.\n"
    )


def _adjust_section(adjust: dict[str, Any] | None) -> str:
    if not adjust:
        return "No logit adjustment (the argmax of the network's own logits)."
    by = ", ".join(f"{a}: {s:.1f} %" for a, s in adjust["val_miou_by_alpha"].items())
    return f"""## Logit adjustment (tools/training/logit_adjust.py)

Class weighting makes the argmax over-predict rare classes; the exported model adds
`-alpha log(w_c)` to each class's logit (Menon et al. 2021), alpha chosen on the validation
worlds below: validation mIoU by alpha {by}; chosen **alpha = {adjust["alpha"]}**, bias
{adjust["bias"]} (also in the metadata `wardmap.logit_bias`)."""


def _input_line(cfg: dict[str, Any], w: int, h: int, sc: int) -> str:
    resize = (f"Frames of another size are resized to {w}x{h} first (`cv2.INTER_AREA`, as the training data\n"
              f"  was made from {w * sc}x{h * sc} renders)")
    if not cfg.get("depth_input"):
        return (f"- input `image`: float32 `[1, 3, {h}, {w}]`, RGB in 0..1 (normalisation is inside the "
                f"model).\n  {resize}.")
    return (f"- input `image`: float32 `[1, 4, {h}, {w}]`: RGB in 0..1, then depth in metres along the "
            f"camera\n  z axis, 0 where the sensor has none (RGB-D; normalisation is inside the model).\n"
            f"  {resize}; depth by nearest neighbour, so holes stay holes.")


def _depth_data(cfg: dict[str, Any], sc: int) -> str:
    if not cfg.get("depth_input"):
        return ""
    return (f"\n- depth: the simulated depth sensor's reading (axial noise, 0.4-8 m range, holes at depth\n"
            f"  edges and on dark, specular and glass materials), one pixel in {sc} along each axis;")


def _depth_augment(cfg: dict[str, Any]) -> str:
    if not cfg.get("depth_input"):
        return ""
    return (";\n  depth follows flip and crop, is divided by the rescale factor (a camera that much\n"
            "  closer), and half the samples get it at half resolution (a robot sending depth at 1/4)")


def _schedule_line(cfg: dict[str, Any], summary: dict[str, Any]) -> str:
    out = []
    if cfg.get("repeat_factor"):
        out.append(f" Frames drawn by repeat-factor sampling (threshold {cfg['repeat_factor']}: a frame\n"
                   "with a class seen in fewer frames comes more often).")
    if cfg.get("time_budget_s"):
        out.append(f" Training capped at {cfg['time_budget_s']:.0f} s of wall time (the schedule\n"
                   f"follows the clock); {summary.get('epochs_run', '?')} epochs run.")
    if cfg.get("select_best"):
        out.append(" The epoch with the best validation mIoU was kept.")
    return "".join(out)


def _machine_words(summary: dict[str, Any]) -> str:
    device, cores = summary.get("device", "CPU"), summary.get("cpu_cores")
    if device == "CPU" and cores in (None, 2):
        return "a 2-core machine shared with other jobs"
    return f"{'' if device == 'CPU' else device + ', '}{cores} CPU cores"


def _site_words(summary: dict[str, Any], cfg: dict[str, Any]) -> str:
    """The site images among the training frames, for the card ('' without any)."""
    n = summary.get("site_frames", 0)
    if not n:
        return ""
    site = cfg["site"]
    sources = ", ".join(f"{k} `{site[k]}`" for k in ("coco_json", "mask_dir", "negatives_dir") if site[k])
    start = f"; started from `{cfg['init_weights']}`" if cfg.get("init_weights") else ""
    return f", of them {n} real site images ({sources}; each {site['repeat']} time(s)){start}"


def model_card(summary: dict[str, Any], metrics: dict[str, Any]) -> str:
    """The Markdown model card of an exported model."""
    cfg = summary["config"]
    d, v = cfg["data"], cfg["val"]
    share = summary["class_pixel_share"]
    rows = "\n".join(
        f"| {k} | {name} | {'-' if iou is None else f'{iou:.1f}'} | {share.get(name, 0):.3f} |"
        for k, (name, iou) in enumerate(metrics["per_class_iou"].items())
    )
    enc = ", ".join(f"({t}, {c}, {n}, {s})" for t, c, n, s in cfg["encoder"])
    w, h, sc = d["width"], d["height"], d["render_scale"]
    nc = len(summary["classes"])
    stop = f" (stopped after {cfg['max_steps']} steps)" if cfg["max_steps"] else ""
    blk = cfg["baff_block_px"]
    mb = summary["onnx_bytes"] / 1e6
    t_all, t_data, t_train = (summary[k] / 60 for k in ("wall_time_s", "data_time_s", "train_time_s"))
    gen = summary.get("data_generation_s", float("nan")) / 60
    cached = (
        f" The samples were loaded from the cache of an earlier run with the same data settings;"
        f" generating them took {'an unrecorded time' if math.isnan(gen) else f'{gen:.1f} min'}."
        if summary.get("data_cached")
        else ""
    )
    return f"""# hospital_seg: hospital semantic segmentation network

Made by `wardmap train-seg` (tools/training/training.py, docs/training.md).

## Interface (ONNX opset {ONNX_OPSET}, one self-contained file, {mb:.2f} MB)

{_input_line(cfg, w, h, sc)}
- output `logits`: float32 `[1, {nc}, {h}, {w}]`; class = argmax over axis 1.
- metadata: `wardmap.classes` = `{json.dumps(summary["classes"])}`;
  `wardmap.input_size` = `{w}x{h}`.

## Classes

Index 0 is background, then the knowledge-graph classes in `shared/data/knowledge_graph.toml`
order (see the table below).

## Architecture (paper 003 Sec. IV-B, Fig. 5)

- Encoder: MobileNetV2-style; stem 3x3/2 conv with {cfg["stem_channels"]} channels, then
  inverted residual stages (expansion, channels, repeats, stride): {enc}; ReLU6, BatchNorm.
- Decoder: from stride 32 up to stride 2. At each level the deeper map is projected and
  bilinearly upsampled, the encoder skip of that stride (stages {cfg["skip_stages"]}) is
  projected to the same channels ({cfg["decoder_channels"]}, deep to shallow), and the two are
  fused by BAFF (Eq. 2: depthwise block convolutions of both maps, sigmoid, 3x3 on the block
  grid, sigmoid, bilinear upsampling, per-pixel convex blend), then refined by a
  depthwise-separable conv. Blocks are {blk}x{blk} input pixels at every level. 1x1
  classifier at stride 2, bilinear to full resolution.
- {summary["parameters"]:,} parameters.

## Training data

Rendered in-process by the wardmap simulator (tools/training/segdata.py), cached by config
hash `{summary["train_data_hash"]}`:

- scenarios: {", ".join(d["scenarios"])};
- world seeds {d["seeds"]} (all < 1000), {d["frames_per_world"]} frames per world,
  {summary["train_frames"]} frames in total{_site_words(summary, cfg)};
- {d["track_fraction"] * 100:.0f} % of frames on the scenario's robot trajectory at a random
  time (scenario people and lighting, including the dark corridor's lights-off phase), the
  rest from random viewpoints in free space (0.7-1.6 m high) looking at an object, rare
  classes favoured (inverse frequency ^ {d["rare_bias"]});
- per world {d["props_per_world"]} free-standing wheelchairs, carts, IV poles and chairs and
  {d["items_per_world"]} cups and temperature guns on furniture; per frame up to
  {d["max_extra_people"]} extra people (random walk phase, height 1.5-1.95 m, heading,
  outfit; 30 % hold a cup or a temperature gun);
- illumination gain {d["light_range"][0]}-{d["light_range"][1]} for random viewpoints;
  rendered at {w * sc}x{h * sc} with the simulator's sensor noise, area-downsampled;{_depth_data(cfg, sc)}
- augmentation: horizontal flip, rescale 0.8-1.25 and {cfg["crop"][0]}x{cfg["crop"][1]} random
  crop, brightness 0.6-1.4, per-channel gain 0.9-1.1, contrast 0.7-1.3, gamma 0.7-1.4,
  Gaussian blur (30 %), noise{_depth_augment(cfg)}.

## Training settings

AdamW, one-cycle learning rate (peak {cfg["lr"]}), weight decay {cfg["weight_decay"]},
batch {cfg["batch_size"]}, {cfg["epochs"]} epochs{stop}, cross-entropy with class weights
(median frequency / frequency) ^ {cfg["class_weight_power"]} clipped at {cfg["max_class_weight"]};
seed {cfg["seed"]}, {cfg["threads"]} torch threads, torch {summary["torch"]} on
{summary.get("device", "CPU")} ({summary["cpu"]}).{_schedule_line(cfg, summary)} Mean loss per epoch:
{summary["epoch_losses"]}.

Command:

```
{summary["command"] or "(library call)"}
```

Wall time {t_all:.1f} min in total (data {t_data:.1f} min, training {t_train:.1f} min, the
rest export and validation) on {_machine_words(summary)}.{cached} ONNX vs torch
max abs logit difference {summary["onnx_torch_max_abs_diff"]:.2e}.

{_adjust_section(summary.get("logit_adjust"))}

## Validation (held-out worlds, seeds >= 1000)

{summary["val_frames"]} frames generated like the training data from worlds never used in
training (scenarios {", ".join(v["scenarios"])}; seeds {v["seeds"]}; {v["frames_per_world"]}
frames each; data hash `{summary["val_data_hash"]}`), scored with numpy on onnxruntime
outputs at {w}x{h}:

- **mIoU {metrics["miou"]:.1f} %** (mean over the classes present in the validation truth),
  pixel accuracy {metrics["pixel_accuracy"]:.1f} %;
- onnxruntime, 1 thread: median {metrics["ms_per_frame"]:.1f} ms per frame.
{_track_line(metrics)}

| index | class | IoU % | training pixel share % |
|---|---|---|---|
{rows}

Training worlds use seeds < 1000 and evaluation worlds seeds >= 1000, so no world is shared.
"""
