"""A site's labelled images for train-seg: COCO JSON (polygons, RLE), CVAT mask PNGs, negatives,
and one short fine-tune on them end to end (torch only there)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.tools.training.segdata import (
    IGNORE_INDEX,
    SegDataConfig,
    SiteDataConfig,
    TrainingError,
    TrainSegConfig,
)
from wardmap.tools.training.sitedata import SITE_WORLD, load_site_samples

coco_mask = pytest.importorskip("pycocotools.mask", reason="COCO site labels need pycocotools")

NAMES = ("background", *KnowledgeGraph.load().names)
W, H = 160, 120


def image(path: Path, seed: int) -> np.ndarray:
    """A random 160 x 120 BGR photograph stand-in written to ``path``."""
    bgr = np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), bgr)
    return bgr


def coco_set(root: Path) -> Path:
    """Three images: a desk (polygon) with a cup on it (compressed RLE), a chair as uncompressed
    RLE, and an image with no annotation (a negative). Category names are the site's."""
    for k in range(3):
        image(root / "img" / f"im{k}.png", k)
    cup = np.zeros((H, W), np.uint8, order="F")
    cup[40:60, 50:70] = 1
    cup_rle = coco_mask.encode(np.asfortranarray(cup))
    cup_rle["counts"] = cup_rle["counts"].decode("ascii")
    chair = np.zeros((H, W), np.uint8)
    chair[10:50, 100:140] = 1
    flat = chair.flatten(order="F")  # COCO RLE runs column-major, starting with zeros
    changes = np.flatnonzero(np.diff(flat)) + 1
    runs = np.diff(np.concatenate([[0], changes, [flat.size]])).tolist()
    doc = {
        "images": [{"id": k + 1, "file_name": f"img/im{k}.png", "width": W, "height": H} for k in range(3)],
        "categories": [{"id": 1, "name": "Table"}, {"id": 2, "name": "cup"},
                       {"id": 3, "name": "office chair"}],
        "annotations": [
            {"id": 1, "image_id": 1, "category_id": 2, "segmentation": cup_rle, "iscrowd": 0},
            {"id": 2, "image_id": 1, "category_id": 1, "iscrowd": 0,
             "segmentation": [[20, 30, 140, 30, 140, 100, 20, 100]]},
            {"id": 3, "image_id": 2, "category_id": 3, "iscrowd": 1,
             "segmentation": {"counts": runs, "size": [H, W]}},
        ],
    }
    path = root / "labels.json"
    path.write_text(json.dumps(doc))
    return path


def mask_set(root: Path) -> Path:
    """A CVAT "Segmentation mask 1.1" export of two images: a person (red) and a monitor (blue);
    'unsure' regions (grey) are to be ignored."""
    (root / "SegmentationClass").mkdir(parents=True)
    (root / "labelmap.txt").write_text(
        "# label:color_rgb:parts:actions\nbackground:0,0,0::\nPerson:255,0,0::\nmonitor:0,0,255::\n"
        "unsure:128,128,128::\n"
    )
    for k in range(2):
        image(root / "JPEGImages" / f"f{k}.jpg", 10 + k)
        mask = np.zeros((H, W, 3), np.uint8)
        mask[20:100, 30:60] = (0, 0, 255)  # BGR red: person
        mask[10:40, 90:150] = (255, 0, 0)  # BGR blue: monitor
        mask[110:120, :] = (128, 128, 128)
        assert cv2.imwrite(str(root / "SegmentationClass" / f"f{k}.png"), mask)
    return root


def site(**kw: object) -> SiteDataConfig:
    return SiteDataConfig(**kw)  # type: ignore[arg-type]


def test_coco_polygons_and_rle_become_our_classes(tmp_path: Path) -> None:
    """The desk polygon is desk except where the cup on it is; the chair's RLE is chair; the
    unannotated image is all background; site names map by class_map or by name."""
    cfg = site(coco_json=str(coco_set(tmp_path)), class_map=(("table", "desk"), ("office chair", "chair")))
    s = load_site_samples(cfg, NAMES, 320, 240)
    assert s is not None and len(s) == 3
    desk, cup, chair = NAMES.index("desk"), NAMES.index("cup"), NAMES.index("chair")
    first = s.classes[0]  # resized 2x (nearest)
    assert np.all(first[82:118, 102:138] == cup)  # the cup keeps its pixels on the desk
    assert np.mean(first[62:200, 42:280] == desk) > 0.9
    assert first[5, 5] == 0
    assert np.all(s.classes[1][22:98, 202:278] == chair)
    assert not s.classes[2].any()
    assert s.rgb.shape == (3, 240, 320, 3) and not s.depth.any()
    assert np.all(s.world == SITE_WORLD) and not s.on_track.any()


def test_mask_pngs_with_a_label_map(tmp_path: Path) -> None:
    """CVAT colours -> classes ('Person' maps by name, case aside; 'monitor' by class_map),
    'ignore' is skipped by the loss, and each image comes ``repeat`` times."""
    cfg = site(mask_dir=str(mask_set(tmp_path / "cvat")),
               class_map=(("unsure", "ignore"), ("monitor", "wall_monitor")), repeat=3)
    s = load_site_samples(cfg, NAMES, W, H)
    assert s is not None and len(s) == 6
    c = s.classes[0]
    assert np.all(c[20:100, 30:60] == NAMES.index("person"))
    assert np.all(c[10:40, 90:150] == NAMES.index("wall_monitor"))
    assert np.all(c[110:, :] == IGNORE_INDEX)
    assert c[0, 0] == 0
    np.testing.assert_array_equal(s.rgb[0], s.rgb[2])  # repeats


def test_negatives_and_depth(tmp_path: Path) -> None:
    """Negatives are all background; a depth PNG named like the image is used, in millimetres."""
    bgr = image(tmp_path / "neg" / "office.png", 3)
    image(tmp_path / "neg" / "hall.jpg", 4)
    depth = np.full((H, W), 1500, np.uint16)
    (tmp_path / "depth").mkdir()
    cv2.imwrite(str(tmp_path / "depth" / "office.png"), depth)
    s = load_site_samples(site(negatives_dir=str(tmp_path / "neg"), depth_dir=str(tmp_path / "depth")),
                          NAMES, W, H)
    assert s is not None and len(s) == 2 and not s.classes.any()
    k = 1  # sorted: hall.jpg, office.png
    np.testing.assert_array_equal(s.rgb[k], bgr[..., ::-1])
    assert np.all(s.depth[k] == 1500) and not s.depth[0].any()


def test_no_site_data_is_none() -> None:
    assert load_site_samples(SiteDataConfig(), NAMES, W, H) is None


def test_bad_site_data_is_one_clear_error(tmp_path: Path) -> None:
    """An unmapped site class, a colour missing from the label map, a missing folder, a
    class_map target that is none of ours: each a TrainingError naming the thing."""
    labels = coco_set(tmp_path / "coco")
    with pytest.raises(TrainingError, match=r"'Table'.*class_map"):
        load_site_samples(site(coco_json=str(labels)), NAMES, W, H)
    with pytest.raises(TrainingError, match="not our classes"):
        load_site_samples(site(coco_json=str(labels), class_map=(("table", "sofa"),)), NAMES, W, H)
    cvat = mask_set(tmp_path / "cvat")
    (cvat / "labelmap.txt").write_text("background:0,0,0::\nperson:255,0,0::\nmonitor:0,0,255::\n")
    with pytest.raises(TrainingError, match=r"\(128,128,128\) are not in labelmap.txt"):
        load_site_samples(site(mask_dir=str(cvat), class_map=(("monitor", "wall_monitor"),)), NAMES, W, H)
    with pytest.raises(TrainingError, match="not found"):
        load_site_samples(site(negatives_dir=str(tmp_path / "nope")), NAMES, W, H)


def test_site_fine_tune_end_to_end(tmp_path: Path) -> None:
    """One short epoch on simulated frames plus a tiny COCO set and a tiny mask-PNG set exports a
    model and its weights; a second run starts from those weights (the site fine-tune path)."""
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from wardmap.tools.training.training import train_and_export

    cfg = TrainSegConfig(
        threads=1,
        cache_dir=str(tmp_path / "cache"),
        data=SegDataConfig(scenarios=("walking_staff",), seeds=(1,), frames_per_world=2),
        val=SegDataConfig(scenarios=("ward_chairs",), seeds=(1001,), frames_per_world=1),
        epochs=1,
        batch_size=2,
        crop=(96, 128),
        depth_input=True,
        device="cpu",
        logit_adjust=(0.0,),
        save_weights=True,
        site=site(coco_json=str(coco_set(tmp_path / "coco")), mask_dir=str(mask_set(tmp_path / "cvat")),
                  class_map=(("table", "desk"), ("office chair", "chair"), ("unsure", "ignore"),
                             ("monitor", "wall_monitor"))),
    )
    first = train_and_export(cfg, tmp_path / "a" / "seg.onnx")
    assert first.summary["site_frames"] == 5 and first.summary["train_frames"] == 7
    weights = tmp_path / "a" / "seg.pt"
    assert weights.is_file()
    assert "of them 5 real site images" in (tmp_path / "a" / "seg.md").read_text()
    tuned = train_and_export(replace(cfg, init_weights=str(weights), save_weights=False),
                             tmp_path / "b" / "seg.onnx", card=False)
    assert (tmp_path / "b" / "seg.onnx").is_file() and not (tmp_path / "b" / "seg.pt").exists()
    assert tuned.summary["site_frames"] == 5
    onnx_start = replace(cfg, init_weights=str(tmp_path / "a" / "seg.onnx"), save_weights=False)
    from_onnx = train_and_export(onnx_start, tmp_path / "d" / "seg.onnx", card=False)
    assert from_onnx.summary["site_frames"] == 5
    with pytest.raises(TrainingError, match="does not fit this network"):
        train_and_export(replace(cfg, init_weights=str(weights), depth_input=False),
                         tmp_path / "c" / "seg.onnx", card=False)


def test_the_packaged_model_reads_back_for_a_fine_tune() -> None:
    """The packaged network's ONNX file (batch norms folded, logit adjustment added) loads into the
    network of deploy/train_seg.toml and reproduces the file's logits (checked inside, 1e-3), so
    a site fine-tune can start from it; a network of another shape is refused with one line."""
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from wardmap.shared.config import load_config
    from wardmap.tools.training.training import BaffSkipNet, _load_weights

    repo = Path(__file__).resolve().parents[3]
    packaged = repo / "server" / "models" / "hospital_seg.onnx"
    cfg = load_config(TrainSegConfig, repo / "deploy" / "train_seg.toml", section="train_seg")
    assert _load_weights(BaffSkipNet(cfg, len(NAMES)), packaged) is True  # batch norms to freeze
    with pytest.raises(TrainingError, match=r"folded convolutions|expected"):
        _load_weights(BaffSkipNet(replace(cfg, stem_channels=8), len(NAMES)), packaged)
