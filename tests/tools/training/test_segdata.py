"""Segmentation training data: determinism, label mapping, augmentation, metrics, config (no torch)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from wardmap.shared.config import from_mapping
from wardmap.shared.errors import ConfigError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.tools.training import segdata
from wardmap.tools.training.segdata import (
    IGNORE_INDEX,
    SegDataConfig,
    TrainSegConfig,
    augment,
    build_samples,
    class_names,
    confusion,
    instance_to_class,
    iou_from_confusion,
    look_at,
    render_world,
    repeat_factors,
)

TINY = SegDataConfig(scenarios=("walking_staff",), seeds=(3,), frames_per_world=3, track_fraction=0.34)


def test_same_seed_same_samples_other_seed_differs() -> None:
    """Rendering one world twice gives identical frames; another seed gives other frames."""
    rgb_a, cls_a, depth_a = render_world("walking_staff", 3, TINY)
    rgb_b, cls_b, depth_b = render_world("walking_staff", 3, TINY)
    assert rgb_a.shape == (3, 240, 320, 3) and rgb_a.dtype == np.uint8
    assert cls_a.shape == (3, 240, 320) and cls_a.dtype == np.uint8
    assert depth_a.shape == (3, 240, 320) and depth_a.dtype == np.uint16
    np.testing.assert_array_equal(rgb_a, rgb_b)
    np.testing.assert_array_equal(cls_a, cls_b)
    np.testing.assert_array_equal(depth_a, depth_b)
    rgb_c, _, _ = render_world("walking_staff", 4, TINY)
    assert not np.array_equal(rgb_a, rgb_c)


def test_depth_is_the_sensor_reading_in_millimetres() -> None:
    """Samples carry the depth sensor's reading: metric (people in front of the camera are
    0.4-8 m away), with holes (0) where the sensor has none, and nothing beyond its range."""
    _, cls, depth = render_world("walking_staff", 3, TINY)
    valid = depth > 0
    assert 0.5 < valid.mean() < 1.0
    assert depth[valid].min() >= 350 and depth[valid].max() <= 8100
    people = (cls == 1) & valid
    assert people.any() and 400 <= np.median(depth[people]) <= 8000


def test_labels_are_knowledge_graph_classes() -> None:
    """Every label is background or a KG class index, and the frames show some objects."""
    kg = KnowledgeGraph.load()
    _, cls, _ = render_world("ward_chairs", 5, TINY, kg, frames=4)
    assert int(cls.max()) <= kg.num_classes
    assert np.count_nonzero(cls) > 0.02 * cls.size
    assert class_names(kg)[0] == "background" and class_names(kg)[1:] == kg.names


def test_instance_to_class_lut() -> None:
    """Instance ids map through the lookup; unknown ids (walls, decor) are background."""
    inst = np.array([[0, 5, 7], [9, 5, 0]], np.uint16)
    out = instance_to_class(inst, {5: 3, 7: 1})
    np.testing.assert_array_equal(out, [[0, 3, 1], [0, 3, 0]])


def test_look_at_points_camera_z_at_target() -> None:
    """The camera z axis points at the target, x stays horizontal, y points down, det = +1."""
    eye, target = np.array([1.0, 2.0, 1.2]), np.array([4.0, -1.0, 0.5])
    T = look_at(eye, target)
    z = (target - eye) / np.linalg.norm(target - eye)
    np.testing.assert_allclose(T[:3, 2], z, atol=1e-12)
    assert abs(T[2, 0]) < 1e-12 and T[2, 1] < 0
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_allclose(T[:3, 3], eye)


def test_augment_keeps_image_and_labels_aligned() -> None:
    """A bright left half labelled 1 and a dark right half labelled 2 stay aligned under flip,
    rescale and crop: labelled-1 pixels stay brighter than labelled-2 pixels."""
    rgb = np.zeros((120, 160, 3), np.uint8)
    rgb[:, :80] = 220
    rgb[:, 80:] = 30
    cls = np.full((120, 160), 2, np.uint8)
    cls[:, :80] = 1
    flips = 0
    for seed in range(12):
        img, lab, none = augment(rgb, cls, np.random.default_rng(seed), crop=(96, 128))
        assert img.shape == (96, 128, 3) and lab.shape == (96, 128) and none is None
        assert set(np.unique(lab)) <= {1, 2, IGNORE_INDEX}
        gray = img.mean(axis=2)
        assert gray[lab == 1].mean() > gray[lab == 2].mean() + 40
        flips += int(lab[:, 0].mean() > 1.5)
    assert 0 < flips < 12  # both orientations occur
    assert rgb[0, 0, 0] == 220 and cls[0, 0] == 1  # inputs untouched


def test_augment_moves_depth_with_the_image() -> None:
    """Depth follows flip and crop (labelled-1 pixels keep their 1 m, labelled-2 their 3 m,
    both divided by the rescale: a zoom by s is a camera s times closer) in metres. Some
    samples get half-resolution depth (2x2 blocks)."""
    rgb = np.full((120, 160, 3), 128, np.uint8)
    cls = np.full((120, 160), 2, np.uint8)
    cls[:, :80] = 1
    depth = np.full((120, 160), 3000, np.uint16)
    depth[:, :80] = 1000
    for seed in range(40):
        _, lab, d = augment(rgb, cls, np.random.default_rng(seed), crop=(96, 128), depth=depth)
        assert d is not None and d.shape == (96, 128) and d.dtype == np.float32
        near, far = d[(lab == 1) & (d > 0)], d[(lab == 2) & (d > 0)]
        # Half-resolution depth may shift the boundary by a pixel: 95 % of pixels, not all.
        near_m = float(np.median(near))
        assert 0.79 < near_m < 1.26 and np.mean(np.abs(near - near_m) < 1e-6) > 0.95
        if far.size:
            assert float(np.median(far)) == pytest.approx(3 * near_m, rel=1e-5)  # one scale per sample
    assert depth[0, 0] == 1000  # input untouched
    ramp = (1000 + 7 * np.arange(160)[None, :] + 3 * np.arange(120)[:, None]).astype(np.uint16)
    coarse = fine = 0
    for seed in range(40):
        _, _, d = augment(rgb, cls, np.random.default_rng(seed), depth=ramp)
        assert d is not None
        coarse += int(np.array_equal(d[0::2, 0::2], d[1::2, 1::2]))
        fine += int(not np.any(d[0::2, 0::2] == d[1::2, 1::2]))
    assert coarse > 5 and fine > 5


def test_confusion_and_iou() -> None:
    """IoU from a hand-computed confusion; a class absent from truth and prediction is NaN."""
    truth = np.array([0, 0, 1, 1, 1, IGNORE_INDEX])
    pred = np.array([0, 1, 1, 1, 0, 2])
    cm = confusion(pred, truth, 3)
    np.testing.assert_array_equal(cm, [[1, 1, 0], [1, 2, 0], [0, 0, 0]])
    iou = iou_from_confusion(cm)
    assert iou[0] == pytest.approx(1 / 3) and iou[1] == pytest.approx(2 / 4) and np.isnan(iou[2])


def test_cache_is_reused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A second build with the same config loads the cache instead of rendering."""
    cfg = SegDataConfig(scenarios=("aisle_slow_1",), seeds=(2,), frames_per_world=2, track_fraction=0.5)
    first = build_samples(cfg, tmp_path)
    assert len(first) == 2 and first.on_track.tolist() == [True, False]

    def fail(*args: object, **kw: object) -> None:
        raise AssertionError("rendered again despite the cache")

    monkeypatch.setattr(segdata, "render_world", fail)
    second = build_samples(cfg, tmp_path)
    np.testing.assert_array_equal(first.rgb, second.rgb)
    np.testing.assert_array_equal(first.classes, second.classes)
    np.testing.assert_array_equal(first.depth, second.depth)
    assert second.names == first.names
    assert not first.cached and second.cached
    assert second.generation_s == pytest.approx(first.generation_s) and first.generation_s > 0


def test_cache_key_follows_the_generator_code(monkeypatch: pytest.MonkeyPatch) -> None:
    """Samples rendered by older simulator code are not reused: the generator's digest is in the key."""
    cfg = SegDataConfig(scenarios=("aisle_slow_1",), seeds=(2,), frames_per_world=2)
    digest = segdata.generator_digest()
    assert len(digest) == 16 and digest == segdata.generator_digest()
    key = segdata.config_hash(cfg)
    monkeypatch.setattr(segdata, "generator_digest", lambda: "0" * 16)
    assert segdata.config_hash(cfg) != key


def test_seed_split_is_enforced() -> None:
    """Training worlds must use seeds < 1000 and validation worlds seeds >= 1000."""
    with pytest.raises(ConfigError, match="training seeds"):
        from_mapping(TrainSegConfig, {"data": {"seeds": [3, 1000]}})
    with pytest.raises(ConfigError, match="validation seeds"):
        from_mapping(TrainSegConfig, {"val": {"seeds": [7]}})
    with pytest.raises(ConfigError, match="unknown scenario"):
        from_mapping(TrainSegConfig, {"data": {"scenarios": ["nowhere"]}})
    with pytest.raises(ConfigError, match="unknown key"):
        from_mapping(TrainSegConfig, {"epoch": 3})


@pytest.mark.parametrize("name", ["train_seg.toml", "train_seg_gpu.toml", "train_seg_site.toml"])
def test_deploy_config_loads(name: str) -> None:
    """deploy/train_seg.toml (the shipped model's), deploy/train_seg_gpu.toml (the GPU recipe) and
    deploy/train_seg_site.toml (a site fine-tune) are valid [train_seg] tables with the
    contract's input size and the seed split."""
    from wardmap.shared.config import load_config

    path = Path(__file__).resolve().parents[3] / "deploy" / name
    cfg = load_config(TrainSegConfig, path, section="train_seg")
    assert (cfg.data.width, cfg.data.height) == (320, 240)
    assert max(cfg.data.seeds) < 1000 <= min(cfg.val.seeds)
    if name == "train_seg_site.toml":  # the packaged model's network, so its weights fit
        shipped = load_config(TrainSegConfig, path.with_name("train_seg.toml"), section="train_seg")
        network = ("depth_input", "stem_channels", "encoder", "skip_stages", "decoder_channels",
                   "baff_block_px")
        for key in network:
            assert getattr(cfg, key) == getattr(shipped, key), key
        assert cfg.init_weights == "server/models/hospital_seg.onnx"


def test_gpu_and_sampling_settings_are_checked() -> None:
    with pytest.raises(ConfigError, match="device must be auto, cpu or cuda"):
        from_mapping(TrainSegConfig, {"device": "tpu"})
    for key in ("time_budget_s", "repeat_factor", "loader_workers"):
        with pytest.raises(ConfigError, match="must be >= 0"):
            from_mapping(TrainSegConfig, {key: -1})


def test_repeat_factors_favour_frames_with_rare_classes() -> None:
    """LVIS rule: a class in a share f of the frames gets max(1, sqrt(t / f)); a frame takes the
    largest factor of its classes; background does not count."""
    classes = np.zeros((10, 4, 4), np.uint8)
    classes[:, 0, 0] = 1  # class 1 in every frame
    classes[0, 1, 1] = 2  # class 2 in one frame of ten
    classes[1:3, 2, 2] = 3  # class 3 in two frames
    r = repeat_factors(classes, 4, threshold=0.4)
    np.testing.assert_allclose(r[0], 2.0)  # sqrt(0.4 / 0.1)
    np.testing.assert_allclose(r[1:3], np.sqrt(2.0))  # sqrt(0.4 / 0.2)
    np.testing.assert_allclose(r[3:], 1.0)
    np.testing.assert_allclose(repeat_factors(classes, 4, threshold=0.0), 1.0)
    assert repeat_factors(np.zeros((3, 2, 2), np.uint8), 4, 0.5).tolist() == [1.0, 1.0, 1.0]
