"""Training and validation samples for the hospital segmentation network, rendered by the simulator.

Pure numpy/OpenCV plus :mod:`wardmap.sim`; no torch. A *world* is one scenario built with
one seed (:func:`wardmap.sim.scenarios.build_scene`). Each world is enriched before
rendering so that every knowledge-graph class is seen often enough:

- free-standing movable objects (wheelchairs, carts, IV poles, chairs) in free space;
- cups and temperature guns on desks, cabinets, carts, beds and sinks;
- per frame, extra people in random walk phases, heights, outfits and headings in front of
  the camera, some holding a cup or a temperature gun.

Frames come from two camera sources: the scenario's own robot trajectory at a random time
(with the scenario's people and lighting), and random viewpoints in free space looking at an
object (rare classes are chosen more often). RGB is rendered at ``render_scale`` times the
network input (640x480 for the default 320x240), with the simulator's lighting gain and
sensor noise, and reduced with ``cv2.INTER_AREA``; labels (instance ids -> class index,
``background`` = 0, then the knowledge-graph order) with ``cv2.INTER_NEAREST``. That is the
preprocessing the deployed model expects (docs/training.md).

Seeds: training worlds use seeds < 1000; evaluation (validation split, benchmarks) uses
seeds >= 1000, so no world is shared.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import multiprocessing
import time
import zlib
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.server.codedigest import code_digest
from wardmap.shared.config import to_mapping
from wardmap.shared.errors import WardmapError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.se3 import make_transform, yaw_transform
from wardmap.sim import models, raster, sensors, textures
from wardmap.sim.geometry import Part, TriangleSoup
from wardmap.sim.live import base_pose
from wardmap.sim.runner import objects_document
from wardmap.sim.scenarios import SCENARIOS, Scene, build_scene
from wardmap.sim.sensors import SensorRig
from wardmap.sim.world import soup_of

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]
U16 = NDArray[np.uint16]
F32 = NDArray[np.float32]
DATA_VERSION: Final = 1
EVAL_SEED_MIN: Final = 1000
IGNORE_INDEX: Final = 255
_VIEW_TRIES: Final = 4
_DEPTH_STREAM: Final = 5000  # frame i's depth noise: stream 5000 + i (RGB uses 1000 + i)
_DEPTH_DROPOUT: Final = sensors.depth_dropout_table()
CACHE_LAYOUT: Final = 2  # 2: samples carry depth; part of the cache key, not of the worlds' seeds
_SURFACE_CLASSES: Final = ("desk", "cabinet", "cart", "bed", "sink")
_PROP_CLASSES: Final = ("wheelchair", "cart", "iv_pole", "chair", "wheelchair", "iv_pole")
_OUTFITS: Final = (
    (60, 110, 170),
    (70, 150, 120),
    (150, 60, 60),
    (170, 200, 230),
    (230, 230, 235),
    (40, 40, 60),
    (120, 90, 160),
    (200, 160, 60),
    (90, 90, 90),
    (180, 80, 120),
)
_SKIN: Final = ((205, 165, 135), (140, 100, 75), (235, 200, 175), (100, 70, 50))
_HAIR: Final = ((60, 40, 25), (200, 180, 120), (20, 20, 20), (150, 150, 150))


class TrainingError(WardmapError):
    """Segmentation training cannot run: missing dependency, bad data or bad settings."""


TRAINING_SCENARIOS: tuple[str, ...] = (
    "aisle_slow_1", "aisle_slow_2", "aisle_slow_3", "aisle_quick_1", "aisle_quick_2", "aisle_quick_3",
    "ward_chairs", "hospital_loop", "walking_staff", "dark_corridor", "two_robots",
)
"""The default training worlds: the scenarios the packaged model was trained on (scenarios added
later, such as ``hospital_days``, stay out so the default training set does not change)."""


@dataclass(frozen=True)
class SegDataConfig:
    """How training or validation frames are generated.

    Attributes:
        scenarios: scenario names (``wardmap.sim.scenarios.SCENARIOS``; default
            :data:`TRAINING_SCENARIOS`).
        seeds: world seeds; every scenario is built with every seed.
        frames_per_world: frames rendered per (scenario, seed) world.
        track_fraction: share of frames taken on the scenario's robot trajectory at a random
            time (scenario people and lighting); the rest are random viewpoints.
        rare_bias: exponent of the inverse class frequency used to choose the object a random
            viewpoint looks at (0: uniform over objects, 1: uniform over classes).
        max_extra_people: up to this many extra people per frame in front of the camera.
        props_per_world: free-standing wheelchairs, carts, IV poles and chairs added per world.
        items_per_world: cups and temperature guns added per world on furniture tops.
        light_range: uniform range of the illumination gain of random viewpoints (1 = normal).
        width, height: network input size in pixels.
        render_scale: render at this multiple of (width, height), then area-downsample.
    """

    scenarios: tuple[str, ...] = TRAINING_SCENARIOS
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 7)
    frames_per_world: int = 40
    track_fraction: float = 0.35
    rare_bias: float = 0.7
    max_extra_people: int = 3
    props_per_world: int = 8
    items_per_world: int = 10
    light_range: tuple[float, float] = (0.35, 1.3)
    width: int = 320
    height: int = 240
    render_scale: int = 2

    def __post_init__(self) -> None:
        unknown = [s for s in self.scenarios if s not in SCENARIOS]
        if unknown:
            raise ValueError(f"unknown scenario(s) {unknown}; known: {', '.join(SCENARIOS)}")
        if not self.scenarios or not self.seeds:
            raise ValueError("scenarios and seeds must not be empty")
        if any(s < 0 for s in self.seeds):
            raise ValueError(f"seeds must be >= 0, got {self.seeds}")
        if self.frames_per_world <= 0:
            raise ValueError(f"frames_per_world must be positive, got {self.frames_per_world}")
        if not 0.0 <= self.track_fraction <= 1.0:
            raise ValueError(f"track_fraction must be in [0, 1], got {self.track_fraction}")
        if not 0.0 < self.light_range[0] <= self.light_range[1]:
            raise ValueError(f"light_range must be 0 < lo <= hi, got {self.light_range}")
        if self.width <= 0 or self.height <= 0 or self.render_scale < 1:
            raise ValueError("width, height and render_scale must be positive")
        if min(self.max_extra_people, self.props_per_world, self.items_per_world) < 0:
            raise ValueError("max_extra_people, props_per_world and items_per_world must be >= 0")


@dataclass(frozen=True)
class SiteDataConfig:
    """A site's labelled images (TOML ``[train_seg.site]``; every path empty = not used).

    Attributes:
        coco_json: a COCO-style instances file (polygons or RLE).
        coco_images: folder the COCO ``file_name`` entries are relative to (default: the
            JSON's folder).
        mask_dir: a CVAT "Segmentation mask" export folder (``labelmap.txt``,
            ``SegmentationClass/``, ``JPEGImages/``).
        negatives_dir: images with no hospital object; every pixel background.
        depth_dir: 16-bit depth PNGs in millimetres named ``<image stem>.png``; images
            without one get depth 0 (no data).
        class_map: ``[site name, our name]`` pairs; our name is a knowledge-graph class,
            ``background`` or ``ignore``.
        repeat: each site image appears this many times per epoch (site images are few
            beside the simulated frames).
    """

    coco_json: str = ""
    coco_images: str = ""
    mask_dir: str = ""
    negatives_dir: str = ""
    depth_dir: str = ""
    class_map: tuple[tuple[str, str], ...] = ()
    repeat: int = 1

    def __post_init__(self) -> None:
        if self.repeat < 1:
            raise ValueError(f"repeat must be >= 1, got {self.repeat}")
        if any(len(pair) != 2 for pair in self.class_map):
            raise ValueError("class_map entries are [site name, our name] pairs")

    @property
    def used(self) -> bool:
        """True when any source is given."""
        return bool(self.coco_json or self.mask_dir or self.negatives_dir)


def _val_data() -> SegDataConfig:
    return SegDataConfig(seeds=(1000,), frames_per_world=16)


@dataclass(frozen=True)
class TrainSegConfig:
    """``wardmap train-seg`` settings (TOML table ``[train_seg]``, see deploy/train_seg.toml).

    Attributes:
        seed: seeds torch, the sample order and the augmentation.
        threads: torch intra-op threads (and onnxruntime threads for validation).
        cache_dir: rendered samples are cached under ``cache_dir/<config hash>/``.
        data: training worlds (seeds must be < 1000).
        val: held-out validation worlds (seeds must be >= 1000).
        depth_input: the network also takes the depth image (RGB-D, a 4-channel input: RGB
            0..1 and depth in metres, 0 = no data); off: RGB only, as in paper 003.
        stem_channels: channels of the stride-2 stem convolution.
        encoder: inverted-residual stages ``(expansion, channels, repeats, stride)``
            (MobileNetV2 Table 2 layout at a small width).
        skip_stages: indices of the encoder stages whose outputs feed the decoder (shallow
            to deep, the last is the decoder's input).
        decoder_channels: channels of each decoder level, deep to shallow (one per skip).
        baff_block_px: BAFF block edge in input pixels (Eq. 2; the block grid is the same at
            every level).
        epochs: passes over the training samples.
        batch_size: samples per step.
        crop: ``(h, w)`` random training crop after rescale.
        lr: peak AdamW learning rate (one-cycle schedule).
        weight_decay: AdamW weight decay.
        class_weight_power: cross-entropy weight ``(median_freq / freq) ** power`` per class.
        max_class_weight: upper clip of the class weights.
        max_steps: stop after this many optimiser steps (0: no limit; smoke tests).
        channels_last: train in NHWC memory layout (about 1.5-2x faster steps on CPU with
            two threads, measured; the exported ONNX file is the same either way).
        logit_adjust: candidate strengths alpha in [0, 1] of the post-hoc logit adjustment
            ``logits - alpha log(w_c)`` that undoes the class weighting's bias toward rare
            classes (``tools/training/logit_adjust.py``); the one with the best
            validation mIoU is baked into the exported model. ``[0]`` turns it off.
        device: ``"auto"`` (CUDA when torch sees a GPU, else CPU), ``"cpu"`` or ``"cuda"``.
        time_budget_s: wall-clock cap of the training loop in seconds (0: none). The
            learning-rate schedule runs on ``max(step / total, elapsed / budget)``, so a run
            stopped by the clock still ends its cycle; such a run is not reproducible.
        repeat_factor: repeat-factor sampling threshold ``t`` (Gupta et al., LVIS, CVPR 2019;
            0: off, every frame once per epoch). A class in a share ``f_c`` of the frames gets
            ``r_c = max(1, sqrt(t / f_c))``; a frame is drawn with probability proportional to
            the largest ``r_c`` of its classes, so frames holding rare classes come more often.
        loader_workers: processes that augment batches (0: in the training loop). The batches
            do not depend on it: each batch's augmentation is seeded by ``(seed, step)``.
        select_best: score the network on the validation worlds after every epoch and keep
            the epoch with the best mIoU (before logit adjustment); off: the last epoch.
        site: a site's own labelled images mixed with the simulated frames
            (``tools/training/sitedata.py``; none by default).
        init_weights: weights to start from instead of random ones (a site fine-tune): an
            exported ``MODEL.onnx`` (batch norms then frozen) or the ``MODEL.pt`` of a run with
            ``save_weights``; its network settings (encoder, decoder, depth input) must be this
            config's.
        save_weights: also write the trained weights as ``MODEL.pt`` beside ``MODEL.onnx`` (the
            ONNX file folds batch norms, so it cannot be trained further).
    """

    seed: int = 0
    threads: int = 2
    cache_dir: str = "out/segdata"
    data: SegDataConfig = field(default_factory=SegDataConfig)
    val: SegDataConfig = field(default_factory=_val_data)
    depth_input: bool = False
    stem_channels: int = 16
    encoder: tuple[tuple[int, int, int, int], ...] = (
        (1, 8, 1, 1),
        (6, 16, 2, 2),
        (6, 24, 3, 2),
        (6, 48, 3, 2),
        (6, 64, 2, 1),
        (6, 96, 2, 2),
    )
    skip_stages: tuple[int, ...] = (0, 1, 2, 4, 5)
    decoder_channels: tuple[int, ...] = (64, 48, 32, 24)
    baff_block_px: int = 16
    epochs: int = 8
    batch_size: int = 8
    crop: tuple[int, int] = (176, 240)
    lr: float = 4e-3
    weight_decay: float = 1e-4
    class_weight_power: float = 0.5
    max_class_weight: float = 10.0
    max_steps: int = 0
    channels_last: bool = True
    logit_adjust: tuple[float, ...] = (0.0, 0.25, 0.5, 0.75, 1.0)
    device: str = "auto"
    time_budget_s: float = 0.0
    repeat_factor: float = 0.0
    loader_workers: int = 0
    select_best: bool = False
    site: SiteDataConfig = field(default_factory=SiteDataConfig)
    init_weights: str = ""
    save_weights: bool = False

    def __post_init__(self) -> None:
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device must be auto, cpu or cuda, got {self.device!r}")
        if self.time_budget_s < 0 or self.repeat_factor < 0 or self.loader_workers < 0:
            raise ValueError("time_budget_s, repeat_factor and loader_workers must be >= 0")
        if any(s >= EVAL_SEED_MIN for s in self.data.seeds):
            raise ValueError(f"training seeds must be < {EVAL_SEED_MIN}, got {self.data.seeds}")
        if any(s < EVAL_SEED_MIN for s in self.val.seeds):
            raise ValueError(f"validation seeds must be >= {EVAL_SEED_MIN}, got {self.val.seeds}")
        if (self.val.width, self.val.height) != (self.data.width, self.data.height):
            raise ValueError("data and val must have the same width and height")
        if self.threads < 1 or self.batch_size < 1 or self.epochs < 1 or self.max_steps < 0:
            raise ValueError("threads, batch_size and epochs must be >= 1, max_steps >= 0")
        if not self.encoder or any(len(s) != 4 or min(s) < 1 for s in self.encoder):
            raise ValueError("encoder stages are (expansion, channels, repeats, stride), all >= 1")
        if sorted(set(self.skip_stages)) != list(self.skip_stages) or not all(
            0 <= i < len(self.encoder) for i in self.skip_stages
        ):
            raise ValueError("skip_stages must be increasing indices of encoder stages")
        if len(self.decoder_channels) != len(self.skip_stages) - 1:
            raise ValueError("decoder_channels needs one entry per skip stage except the deepest")
        if self.baff_block_px < 1 or self.crop[0] < 32 or self.crop[1] < 32:
            raise ValueError("baff_block_px must be >= 1 and crop at least 32x32")
        if self.crop[0] > self.data.height or self.crop[1] > self.data.width:
            raise ValueError(
                f"crop {self.crop} is larger than the image {self.data.height}x{self.data.width}"
            )
        if self.lr <= 0 or self.weight_decay < 0 or self.max_class_weight < 1:
            raise ValueError("lr must be > 0, weight_decay >= 0, max_class_weight >= 1")
        if not self.logit_adjust or not all(0.0 <= a <= 1.0 for a in self.logit_adjust):
            raise ValueError(f"logit_adjust needs strengths in [0, 1] (0 = off), got {self.logit_adjust}")


@dataclass(frozen=True)
class SegSamples:
    """Rendered samples.

    Attributes:
        rgb: uint8 (N, H, W, 3) RGB.
        classes: uint8 (N, H, W) class index per pixel (0 background, then KG order).
        depth: uint16 (N, H, W) depth sensor reading in millimetres along the camera z axis,
            0 = no data.
        world: int32 (N,) index of the (scenario, seed) world each frame comes from.
        on_track: bool (N,) True for frames on the scenario's robot trajectory.
        names: class names in index order, ``background`` first.
        generation_s: seconds it took to render them (NaN if not recorded).
        cached: True when they were loaded from the cache.
    """

    rgb: U8
    classes: U8
    depth: U16
    world: NDArray[np.int32]
    on_track: NDArray[np.bool_]
    names: tuple[str, ...] = field(default=())
    generation_s: float = float("nan")
    cached: bool = False

    def __len__(self) -> int:
        return int(self.rgb.shape[0])

    def subset(self, keep: NDArray[np.bool_]) -> SegSamples:
        """The frames where ``keep`` (N,) is True."""
        return SegSamples(
            self.rgb[keep], self.classes[keep], self.depth[keep], self.world[keep], self.on_track[keep],
            self.names,
        )

    def plus(self, other: SegSamples) -> SegSamples:
        """These frames, then ``other``'s (same size and class names); generation time and cache
        state are this set's."""
        if other.names != self.names or other.rgb.shape[1:] != self.rgb.shape[1:]:
            raise TrainingError(f"cannot join samples of {other.rgb.shape[1:3]} and classes {other.names} to "
                                f"samples of {self.rgb.shape[1:3]} and classes {self.names}")
        return SegSamples(
            np.concatenate([self.rgb, other.rgb]), np.concatenate([self.classes, other.classes]),
            np.concatenate([self.depth, other.depth]), np.concatenate([self.world, other.world]),
            np.concatenate([self.on_track, other.on_track]), self.names, self.generation_s, self.cached,
        )


def class_names(kg: KnowledgeGraph) -> tuple[str, ...]:
    """Segmentation class names in index order: ``background`` then the KG classes."""
    return ("background", *kg.names)


@functools.cache
def generator_digest() -> str:
    """Hex digest of what renders the samples: the simulator package's modules, this module and
    the packaged knowledge graph (file names and bytes). Part of the cache key, so a change to
    the simulator (a new wall decoration, another texture) renders the data anew instead of
    training on samples of the old code."""
    sim_dir = Path(models.__file__).resolve().parent
    return code_digest([*sorted(sim_dir.glob("*.py")), Path(__file__).resolve()])


def config_hash(cfg: SegDataConfig) -> str:
    """Hex digest of the data config, the data version and :func:`generator_digest` (the cache key)."""
    blob = json.dumps(
        {"version": DATA_VERSION, "layout": CACHE_LAYOUT, "generator": generator_digest(),
         "config": to_mapping(cfg)}, sort_keys=True
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


# ---- world enrichment --------------------------------------------------------------------


@dataclass
class _World:
    """A scene ready to render: enriched static props, class lookup, texture atlas."""

    scene: Scene
    props: TriangleSoup | None
    id_to_class: dict[int, int]
    objects: list[tuple[int, F64, F64]]  # (class index, centre (3,), size (3,)) of every object
    object_ids: list[int]  # instance id of each entry of ``objects``
    next_id: int
    atlas: raster.MipAtlas
    people: list[tuple[str, str, str]]  # (outfit, face, hair) texture names


def _inside_free(scene: Scene, xy: F64, margin: float) -> bool:
    return any(
        r.x0 + margin <= xy[0] <= r.x1 - margin and r.y0 + margin <= xy[1] <= r.y1 - margin
        for r in scene.world.free
    )


def _clear_of(objects: list[tuple[int, F64, F64]], xy: F64, margin: float) -> bool:
    return all(np.hypot(*(xy - c[:2])) >= 0.5 * float(np.hypot(s[0], s[1])) + margin for _, c, s in objects)


def _track_points(scene: Scene) -> F64:
    return np.concatenate([np.column_stack([r.track.x, r.track.y]) for r in scene.robots])


def _prepare_world(scene: Scene, cfg: SegDataConfig, kg: KnowledgeGraph, rng: np.random.Generator) -> _World:
    world = scene.world
    doc = objects_document(scene, np.zeros(1), kg)
    id_to_class: dict[int, int] = {}
    objects: list[tuple[int, F64, F64]] = []
    object_ids: list[int] = []
    for o in doc["objects"]:  # type: ignore[attr-defined]
        ci = kg.index_of(str(o["class"]))
        id_to_class[int(o["id"])] = ci
        T = np.asarray(o["T_world_object"], np.float64)
        objects.append((ci, T[:3, 3], np.asarray(o["size"], np.float64)))
        object_ids.append(int(o["id"]))
    next_id = max([world.next_id, *(i + 1 for i in id_to_class)])

    bank = world.bank
    people: list[tuple[str, str, str]] = []
    for k in range(6):
        col = _OUTFITS[int(rng.integers(len(_OUTFITS)))]
        outfit = f"seg_outfit_{k}"
        if k % 2 == 0:
            bank.add(outfit, textures.scrubs(rng, col))
        else:
            bank.add(outfit, textures.fabric(rng, col, pattern=True))
        face, hair = f"seg_face_{k}", f"seg_hair_{k}"
        bank.add(face, textures.skin_face(rng, _SKIN[k % len(_SKIN)]))
        bank.add(hair, textures.hair(rng, _HAIR[int(rng.integers(len(_HAIR)))]))
        people.append((outfit, face, hair))
    for name, maker in (
        ("seg_cart_front", lambda g: textures.panelled(g, (200, 215, 230), 4, 1)),
        ("seg_chair_seat", lambda g: textures.fabric(g, (60, 130, 80), pattern=True)),
    ):
        if name not in bank:
            bank.add(name, maker(rng))

    soups: list[TriangleSoup] = []
    path = _track_points(scene)

    def add(cls: str, parts: tuple[Part, ...], T_world_model: F64) -> None:
        nonlocal next_id
        soups.append(soup_of(parts, T_world_model, next_id, bank))
        lo = np.min([np.asarray(p.center) - np.asarray(p.size) / 2 for p in parts], axis=0)
        hi = np.max([np.asarray(p.center) + np.asarray(p.size) / 2 for p in parts], axis=0)
        centre = (T_world_model @ np.append((lo + hi) / 2, 1.0))[:3]
        id_to_class[next_id] = kg.index_of(cls)
        objects.append((kg.index_of(cls), centre, hi - lo))
        object_ids.append(next_id)
        next_id += 1

    for _ in range(cfg.props_per_world):
        cls = str(rng.choice(_PROP_CLASSES))
        for _try in range(30):
            r = world.free[int(rng.integers(len(world.free)))]
            xy = np.array([rng.uniform(r.x0, r.x1), rng.uniform(r.y0, r.y1)])
            if (
                _inside_free(scene, xy, 0.5)
                and _clear_of(objects, xy, 0.4)
                and np.min(np.hypot(*(path - xy).T)) > 0.9
            ):
                parts = {
                    "wheelchair": models.wheelchair,
                    "cart": lambda: models.cart("seg_cart_front"),
                    "iv_pole": models.iv_pole,
                    "chair": lambda: models.chair("seg_chair_seat"),
                }[cls]()
                add(cls, parts, yaw_transform(float(xy[0]), float(xy[1]), float(rng.uniform(-np.pi, np.pi))))
                break

    surfaces = [(c, s) for ci, c, s in objects if kg.name_of(ci) in _SURFACE_CLASSES]
    for _ in range(cfg.items_per_world if surfaces else 0):
        centre, size = surfaces[int(rng.integers(len(surfaces)))]
        cls = "cup" if rng.random() < 0.5 else "temperature_gun"
        parts = models.cup() if cls == "cup" else models.temperature_gun()
        half = np.maximum(size[:2] / 2 - 0.12, 0.0)
        xy = centre[:2] + rng.uniform(-1, 1, 2) * half
        T = yaw_transform(
            float(xy[0]), float(xy[1]), float(rng.uniform(-np.pi, np.pi)), float(centre[2] + size[2] / 2)
        )
        add(cls, parts, T)

    atlas = raster.build_mipmaps(bank.stack())
    props = TriangleSoup.concat(soups) if soups else None
    return _World(scene, props, id_to_class, objects, object_ids, next_id, atlas, people)


# ---- frames ------------------------------------------------------------------------------


def look_at(eye: F64, target: F64, roll: float = 0.0) -> F64:
    """``T_world_camera`` (4, 4) of a camera at ``eye`` (3,) looking at ``target`` (3,), metres.

    Camera frame: x right, y down, z forward; world z up. ``roll`` (radians) turns about z.
    """
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    return make_transform(np.column_stack([x, y, z]), eye)


def _random_view(
    w: _World, cfg: SegDataConfig, rng: np.random.Generator, kg: KnowledgeGraph
) -> tuple[F64, int]:
    """``(T_world_camera, target instance id or 0)``: a pose in free space, usually looking at
    an object (rare classes favoured)."""
    scene = w.scene
    counts = np.bincount([c for c, _, _ in w.objects], minlength=kg.num_classes + 1).astype(np.float64)
    if w.objects and rng.random() < 0.85:
        weights = np.array([counts[c] ** -cfg.rare_bias for c, _, _ in w.objects])
        for _try in range(40):
            k = int(rng.choice(len(w.objects), p=weights / weights.sum()))
            _, centre, size = w.objects[k]
            target = centre + rng.normal(0, 0.15, 3) * np.minimum(size, 0.5)
            dist = rng.uniform(0.8, 4.5) if size.max() > 0.3 else rng.uniform(0.5, 2.2)
            ang = rng.uniform(-np.pi, np.pi)
            eye = np.array(
                [target[0] + dist * np.cos(ang), target[1] + dist * np.sin(ang), rng.uniform(0.7, 1.6)]
            )
            if _inside_free(scene, eye[:2], 0.25) and _clear_of(w.objects, eye[:2], 0.2):
                return look_at(eye, target, float(rng.normal(0, 0.05))), w.object_ids[k]
    for _try in range(100):
        r = scene.world.free[int(rng.integers(len(scene.world.free)))]
        eye = np.array([rng.uniform(r.x0, r.x1), rng.uniform(r.y0, r.y1), rng.uniform(0.7, 1.6)])
        if _inside_free(scene, eye[:2], 0.25) and _clear_of(w.objects, eye[:2], 0.2):
            yaw, pitch = rng.uniform(-np.pi, np.pi), rng.uniform(-0.35, 0.1)
            d = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
            return look_at(eye, eye + d, float(rng.normal(0, 0.05))), 0
    raise TrainingError(f"world {scene.name}:{scene.seed}: no free camera position found")


def _extra_people(
    w: _World, T_world_camera: F64, rng: np.random.Generator, max_people: int, first_id: int
) -> tuple[list[TriangleSoup], dict[int, int], int]:
    """Posed people (and what they hold) on the floor in front of the camera."""
    kg_person, soups, classes = 1, [], {}
    pid = first_id
    eye, fwd = T_world_camera[:3, 3], T_world_camera[:3, 2]
    heading = float(np.arctan2(fwd[1], fwd[0]))
    for _ in range(int(rng.integers(0, max_people + 1))):
        for _try in range(10):
            a = heading + rng.uniform(-0.5, 0.5)
            d = rng.uniform(0.9, 6.0)
            xy = eye[:2] + d * np.array([np.cos(a), np.sin(a)])
            if _inside_free(w.scene, xy, 0.25) and _clear_of(w.objects, xy, 0.1):
                break
        else:
            continue
        outfit, face, hair = w.people[int(rng.integers(len(w.people)))]
        height = float(rng.uniform(1.5, 1.95))
        holds = rng.random() < 0.3
        parts = models.person(
            outfit,
            face,
            hair,
            float(rng.uniform(0, 2 * np.pi)),
            height=height,
            arms_forward=holds or rng.random() < 0.2,
        )
        T_model = yaw_transform(float(xy[0]), float(xy[1]), float(rng.uniform(-np.pi, np.pi)))
        soups.append(soup_of(parts, T_model, pid, w.scene.world.bank))
        classes[pid] = kg_person
        pid += 1
        if holds:
            k = height / 1.75
            T_hand = T_model @ yaw_transform(0.45, float(rng.choice([-0.27, 0.27])), 0.0, 0.86 * k + 0.3)
            is_cup = rng.random() < 0.5
            item = models.cup() if is_cup else models.temperature_gun()
            soups.append(soup_of(item, T_hand, pid, w.scene.world.bank))
            classes[pid] = 6 if is_cup else 5  # KG order: temperature_gun 5, cup 6 (checked at load)
            pid += 1
    return soups, classes, pid


def _render(
    w: _World,
    T_world_camera: F64,
    dynamic: list[TriangleSoup],
    light: float,
    cfg: SegDataConfig,
    rng: np.random.Generator,
    depth_rng: np.random.Generator,
) -> tuple[U8, NDArray[np.uint16], U16]:
    """RGB (h, w, 3) uint8, instance ids (h, w) and depth (h, w) uint16 mm at the network size.

    Depth is the simulated sensor's reading (noise, range, holes; :func:`sensors.depth_noise`)
    at render size, subsampled every ``render_scale`` pixels as the edge subsamples depth for
    the wire. Its noise comes from ``depth_rng`` so the RGB does not depend on it.
    """
    rig = SensorRig()
    sc = cfg.render_scale
    W, H = cfg.width * sc, cfg.height * sc
    f = 525.0 * W / 640.0
    parts = [w.scene.world.static, *([w.props] if w.props is not None else []), *dynamic]
    soup = TriangleSoup.concat(parts)
    mesh = raster.Mesh(soup.vertices, soup.uv, soup.texture, soup.instance, soup.material, soup.shade)
    out = raster.render(
        mesh,
        w.atlas,
        (f, f, (W - 1) / 2, (H - 1) / 2),
        W,
        H,
        np.linalg.inv(T_world_camera),
        sample_gray=False,
    )
    if out.color is None:
        raise TrainingError("renderer returned no colour")
    from wardmap.sim.materials import MATERIALS

    emissive = np.array([m.emissive for m in MATERIALS], bool)
    gain = np.where(emissive[out.material], np.float32(max(light, 0.8)), np.float32(light))
    noise = rng.standard_normal(size=out.color.shape, dtype=np.float32) * np.float32(rig.rgb_noise_std)
    rgb = np.clip(out.color * (255.0 * gain)[..., None] + noise + 0.5, 0, 255).astype(np.uint8)
    if sc > 1:
        rgb = np.asarray(cv2.resize(rgb, (cfg.width, cfg.height), interpolation=cv2.INTER_AREA), np.uint8)
        inst = np.asarray(
            cv2.resize(out.instance, (cfg.width, cfg.height), interpolation=cv2.INTER_NEAREST), np.uint16
        )
    else:
        inst = out.instance
    depth = sensors.depth_noise(out.depth, out.material, rig, _DEPTH_DROPOUT, depth_rng)
    depth_mm = np.round(depth[::sc, ::sc] * 1000.0).clip(0, 65535).astype(np.uint16)
    return rgb, inst, depth_mm


def instance_to_class(instances: NDArray[np.uint16], id_to_class: dict[int, int]) -> U8:
    """Class index image (H, W) uint8 from instance ids (H, W); ids not in the map are background."""
    lut = np.zeros(int(max([int(instances.max()), *id_to_class])) + 1, np.uint8)
    for i, c in id_to_class.items():
        lut[i] = c
    return lut[instances]


def world_rng(scenario: str, seed: int, stream: int) -> np.random.Generator:
    """The deterministic generator of one world (scenario name, seed, stream)."""
    return np.random.default_rng([seed, zlib.crc32(scenario.encode()), stream, DATA_VERSION])


def render_world(
    scenario: str, seed: int, cfg: SegDataConfig, kg: KnowledgeGraph | None = None, frames: int | None = None
) -> tuple[U8, U8, U16]:
    """Render ``frames`` (default ``cfg.frames_per_world``) samples of one world.

    Returns:
        ``(rgb (n, H, W, 3) uint8, classes (n, H, W) uint8, depth (n, H, W) uint16 mm, 0 = no
        data)``; the same arguments always give identical arrays.
    """
    kg = kg or KnowledgeGraph.load()
    if (kg.index_of("temperature_gun"), kg.index_of("cup"), kg.index_of("person")) != (5, 6, 1):
        raise TrainingError("knowledge graph class order changed; update segdata's held-item classes")
    n = cfg.frames_per_world if frames is None else frames
    scene = build_scene(scenario, seed)
    rng = world_rng(scenario, seed, 0)
    w = _prepare_world(scene, cfg, kg, rng)
    rig = SensorRig()
    rgb = np.empty((n, cfg.height, cfg.width, 3), np.uint8)
    cls = np.empty((n, cfg.height, cfg.width), np.uint8)
    depth = np.empty((n, cfg.height, cfg.width), np.uint16)
    n_track = round(n * cfg.track_fraction)
    for i in range(n):
        frng = world_rng(scenario, seed, 1000 + i)
        t = float(frng.uniform(0.0, scene.duration))
        if i < n_track:
            run = scene.robots[int(frng.integers(len(scene.robots)))]
            T_wc = base_pose(run, np.array([min(t, float(run.track.t[-1]))]))[0] @ rig.T_base_rgb
            light = scene.light(t)
            max_people = min(1, cfg.max_extra_people)
        else:
            light = float(frng.uniform(*cfg.light_range))
            max_people = cfg.max_extra_people
        dyn = [soup_of(*a.at(t), a.id, scene.world.bank) for a in scene.actors]
        drng = world_rng(scenario, seed, _DEPTH_STREAM + i)
        for attempt in range(_VIEW_TRIES):
            if i >= n_track:
                T_wc, target = _random_view(w, cfg, frng, kg)
            extra, extra_cls, _ = _extra_people(w, T_wc, frng, max_people, w.next_id)
            img, inst, dmm = _render(w, T_wc, dyn + extra, light, cfg, frng, drng)
            # A random view whose target is hidden (behind a wall) is drawn again.
            if (
                i < n_track
                or target == 0
                or attempt == _VIEW_TRIES - 1
                or np.count_nonzero(inst == target) >= 30
            ):
                break
        rgb[i] = img
        depth[i] = dmm
        cls[i] = instance_to_class(inst, {**w.id_to_class, **extra_cls})
    return rgb, cls, depth


def _render_world_job(job: tuple[str, int, SegDataConfig]) -> tuple[U8, U8, U16]:
    return render_world(*job)


def build_samples(
    cfg: SegDataConfig,
    cache_dir: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
    kg: KnowledgeGraph | None = None,
    workers: int = 1,
) -> SegSamples:
    """Render every world of ``cfg`` (or load them from ``cache_dir/<config hash>/``).

    ``workers`` > 1 renders worlds in that many processes (same result).

    Raises:
        TrainingError: the cache cannot be written or read.
    """
    kg = kg or KnowledgeGraph.load()
    names = class_names(kg)
    target: Path | None = None
    if cache_dir is not None:
        target = Path(cache_dir) / config_hash(cfg) / "samples.npz"
        if target.is_file():
            try:
                with np.load(target) as z:
                    if tuple(str(s) for s in z["names"]) == names:
                        log.info("segmentation data: cached %s", target)
                        gen = float(z["generation_s"]) if "generation_s" in z.files else float("nan")
                        return SegSamples(
                            z["rgb"], z["classes"], z["depth"], z["world"], z["on_track"], names, gen,
                            cached=True,
                        )
                    log.info("segmentation data: %s has other class names; rendering again", target)
            except (OSError, KeyError, ValueError) as exc:
                raise TrainingError(f"corrupt data cache {target}: {exc}; delete it to regenerate") from exc
    started = time.perf_counter()
    worlds = [(s, seed) for s in cfg.scenarios for seed in cfg.seeds]
    rgbs, clss, depths, widx, track = [], [], [], [], []
    results: Iterator[tuple[U8, U8, U16]]
    pool = None
    if workers > 1 and len(worlds) > 1:
        # Worlds are independent and seeded: the result does not depend on the worker count.
        pool = ProcessPoolExecutor(min(workers, len(worlds)), mp_context=multiprocessing.get_context("spawn"))
        results = pool.map(_render_world_job, [(sc, sd, cfg) for sc, sd in worlds])
    else:
        results = (render_world(sc, sd, cfg, kg) for sc, sd in worlds)
    try:
        for k, (rgb, cls, depth) in enumerate(results):
            rgbs.append(rgb)
            clss.append(cls)
            depths.append(depth)
            widx.append(np.full(len(rgb), k, np.int32))
            track.append(np.arange(len(rgb)) < round(len(rgb) * cfg.track_fraction))
            if progress is not None:
                progress(k + 1, len(worlds))
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    samples = SegSamples(
        np.concatenate(rgbs),
        np.concatenate(clss),
        np.concatenate(depths),
        np.concatenate(widx),
        np.concatenate(track),
        names,
        time.perf_counter() - started,
    )
    if target is not None:
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = target.with_suffix(".tmp.npz")
            np.savez(
                tmp,
                rgb=samples.rgb,
                classes=samples.classes,
                depth=samples.depth,
                world=samples.world,
                on_track=samples.on_track,
                names=np.array(names),
                generation_s=np.float64(samples.generation_s),
            )
            tmp.replace(target)
            (target.parent / "config.json").write_text(
                json.dumps(to_mapping(cfg), indent=2, sort_keys=True) + "\n"
            )
        except OSError as exc:
            raise TrainingError(f"cannot write data cache {target}: {exc}") from exc
    return samples


# ---- augmentation ------------------------------------------------------------------------


def augment(
    rgb: U8,
    classes: U8,
    rng: np.random.Generator,
    crop: tuple[int, int] | None = None,
    depth: U16 | None = None,
) -> tuple[U8, U8, F32 | None]:
    """Photometric and geometric augmentation of one sample (new arrays, inputs untouched).

    Args:
        rgb: uint8 (H, W, 3); classes: uint8 (H, W).
        crop: ``(h, w)`` random crop after a random rescale (0.8..1.25); None keeps the size.
        depth: uint16 (H, W) millimetres, 0 = no data, or None.

    Returns:
        ``(rgb, classes, depth)``; pixels outside the source after rescale/crop are
        :data:`IGNORE_INDEX`. Applied: horizontal flip, brightness, contrast, gamma,
        colour cast, Gaussian blur, sensor noise. Depth (float32 (h, w) metres, None without
        one) follows the flip and crop; a rescale by ``s`` stands for a camera ``s`` times
        closer, so depth is divided by ``s``; half the samples get depth at half resolution
        (every other pixel repeated), as the server gets it from a robot sending depth at 1/4
        (``agent.depth_stride = 4``).
    """
    img = rgb.astype(np.float32) / 255.0
    lab = classes
    dep = None if depth is None else depth.astype(np.float32) * np.float32(0.001)
    if rng.random() < 0.5:
        img, lab = img[:, ::-1], lab[:, ::-1]
        dep = None if dep is None else dep[:, ::-1]
    if crop is not None:
        s = float(rng.uniform(0.8, 1.25))
        h, w = lab.shape
        nh, nw = max(round(h * s), crop[0]), max(round(w * s), crop[1])
        img = np.asarray(cv2.resize(img, (nw, nh), interpolation=cv2.INTER_LINEAR), np.float32)
        lab = np.asarray(
            cv2.resize(np.ascontiguousarray(lab), (nw, nh), interpolation=cv2.INTER_NEAREST), np.uint8
        )
        y0 = int(rng.integers(0, nh - crop[0] + 1))
        x0 = int(rng.integers(0, nw - crop[1] + 1))
        img = img[y0 : y0 + crop[0], x0 : x0 + crop[1]]
        lab = lab[y0 : y0 + crop[0], x0 : x0 + crop[1]]
        if dep is not None:
            dep = np.asarray(
                cv2.resize(np.ascontiguousarray(dep), (nw, nh), interpolation=cv2.INTER_NEAREST), np.float32
            )[y0 : y0 + crop[0], x0 : x0 + crop[1]] / np.float32(s)
    img = img * np.float32(rng.uniform(0.6, 1.4)) * rng.uniform(0.9, 1.1, 3).astype(np.float32)
    mean = img.mean()
    img = (img - mean) * np.float32(rng.uniform(0.7, 1.3)) + mean
    img = np.clip(img, 0.0, 1.0) ** np.float32(rng.uniform(0.7, 1.4))
    if rng.random() < 0.3:
        img = cv2.GaussianBlur(img, (0, 0), float(rng.uniform(0.4, 1.5)))
    img = img + rng.standard_normal(img.shape, dtype=np.float32) * np.float32(rng.uniform(0.0, 0.03))
    out = np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if dep is not None:
        h, w = dep.shape
        if rng.random() < 0.5:
            dep = np.repeat(np.repeat(dep[::2, ::2], 2, axis=0), 2, axis=1)[:h, :w]
        dep = np.ascontiguousarray(dep, np.float32)
    return np.ascontiguousarray(out), np.ascontiguousarray(lab), dep


def class_weights(
    classes: NDArray[np.uint8], num_classes: int, power: float, max_weight: float
) -> NDArray[np.float32]:
    """Cross-entropy weights (C,): ``(median_freq / freq_c) ** power``, clipped to [1/max, max].

    Classes absent from the data get ``max_weight``.
    """
    counts = np.bincount(classes.reshape(-1), minlength=256)[:num_classes].astype(np.float64)
    freq = counts / max(counts.sum(), 1.0)
    med = float(np.median(freq[freq > 0])) if np.any(freq > 0) else 1.0
    w = np.where(freq > 0, (med / np.maximum(freq, 1e-12)) ** power, max_weight)
    return np.clip(w, 1.0 / max_weight, max_weight).astype(np.float32)


def repeat_factors(classes: NDArray[np.uint8], num_classes: int, threshold: float) -> NDArray[np.float64]:
    """Repeat factor (N,) of each frame for repeat-factor sampling (Gupta et al., LVIS, CVPR 2019).

    ``classes``: uint8 (N, H, W) class images. A class present in a share ``f_c`` of the
    frames gets ``r_c = max(1, sqrt(threshold / f_c))``; a frame gets the largest ``r_c`` of
    the classes in it (background, index 0, excluded; a frame of background only gets 1).
    ``threshold`` 0 gives all ones.
    """
    n = classes.shape[0]
    present = np.zeros((n, num_classes), bool)
    for i in range(n):
        present[i] = np.bincount(classes[i].reshape(-1), minlength=256)[:num_classes] > 0
    present[:, 0] = False
    share = present.mean(axis=0)
    with np.errstate(divide="ignore"):
        r_c = np.where(share > 0, np.sqrt(threshold / np.maximum(share, 1e-12)), 1.0)
    r_c = np.maximum(r_c, 1.0)
    return np.where(present, r_c[None], 1.0).max(axis=1)


def confusion(pred: NDArray[np.integer], truth: NDArray[np.integer], n: int) -> NDArray[np.int64]:
    """Confusion matrix (n, n) counting ``truth`` rows against ``pred`` columns (ignore >= n)."""
    t = truth.reshape(-1).astype(np.int64)
    p = pred.reshape(-1).astype(np.int64)
    keep = t < n
    return np.bincount(t[keep] * n + p[keep], minlength=n * n).reshape(n, n)


def iou_from_confusion(cm: NDArray[np.int64]) -> NDArray[np.float64]:
    """Per-class IoU (n,) = TP / (TP + FP + FN); NaN where a class never occurs nor is predicted."""
    tp = np.diag(cm).astype(np.float64)
    union = cm.sum(0) + cm.sum(1) - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, tp / np.maximum(union, 1), np.nan)
