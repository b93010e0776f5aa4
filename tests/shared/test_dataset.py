"""Tests of wardmap.shared.dataset: round trips, determinism, real TUM data, malformed input."""

from __future__ import annotations

import os
import shutil
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tomli_w

from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import (
    TUM_CAMERAS,
    Calibration,
    DatasetReader,
    DatasetWriter,
    associate_stamps,
    decode_scaled_uint16,
    encode_scaled_uint16,
    load_calibration,
    pose_at,
    save_calibration,
    tum_camera_for_folder,
)
from wardmap.shared.errors import DatasetError
from wardmap.shared.se3 import se3_exp

TUM_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tum_fr1_rpy_s3_first100"
needs_tum = pytest.mark.skipif(not TUM_DIR.is_dir(), reason=f"reference data absent: {TUM_DIR}")

W, H = 64, 48
TW, TH = 32, 24
T0 = 1_700_000_000.0


def random_pose(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    return se3_exp(np.concatenate([rng.normal(0, scale, 3), rng.normal(0, 0.5, 3)]))


def make_calibration(rng: np.random.Generator) -> Calibration:
    return Calibration(
        rgb=PinholeCamera(W, H, 50.5, 51.25, 31.5, 23.5, (0.01, -0.002, 0.0005, -0.0003, 0.0)),
        depth_scale=5000.0,
        thermal=PinholeCamera(TW, TH, 30.0, 30.0, 15.5, 11.5),
        T_rgb_thermal=random_pose(rng, 0.05),
        thermal_scale=100.0,
        T_base_rgb=random_pose(rng, 0.3),
        wheel_radius_m=0.035,
        wheel_base_m=0.23,
        ticks_per_mm=11.7,
    )


def write_synthetic(root: Path, seed: int = 7, n: int = 3, **writer_kw: Any) -> dict[str, Any]:
    """Write a small synthetic data set (n frames of 64x48) and return what was written."""
    rng = np.random.default_rng(seed)
    calib = make_calibration(rng)
    stamps = T0 + 0.1 * np.arange(n)
    rgb = rng.integers(0, 256, size=(n, H, W, 3), dtype=np.uint8)
    depth = rng.uniform(0.3, 10.0, size=(n, H, W)).astype(np.float32)
    depth[:, :5, :] = 0.0  # a band without data
    thermal = rng.uniform(290.0, 310.0, size=(n, TH, TW)).astype(np.float32)
    labels = rng.integers(0, 600, size=(n, H, W)).astype(np.uint16)
    poses = np.stack([random_pose(rng) for _ in range(n)])
    odo_stamps = T0 + 0.02 * np.arange(11)
    odo_poses = np.stack([random_pose(rng) for _ in range(11)])
    ticks = np.cumsum(rng.integers(0, 200, size=(11, 2)), axis=0).astype(np.float64)
    encoders = np.column_stack([odo_stamps, ticks, rng.normal(0, 0.3, 11)])
    objects = {
        "world": {"name": "ward-a", "frame": "world"},
        "classes": {"bed": "static", "wheelchair": "movable"},
        "objects": [
            {"id": 1, "class": "bed", "mobility": "static",
             "T_world_object": np.eye(4).tolist(), "size": [2.0, 1.0, 0.6]},
            {"id": 2, "class": "wheelchair", "mobility": "movable",
             "T_world_object": poses[0].tolist(), "size": [1.0, 0.6, 0.9],
             "trajectory": [{"stamp": float(s), "T_world_object": p.tolist()}
                            for s, p in zip(stamps, poses, strict=True)]},
        ],
    }
    with DatasetWriter(root, calib, **writer_kw) as w:
        for i in range(n):
            w.write_frame(float(stamps[i]), rgb[i], depth[i], thermal_k=thermal[i],
                          thermal_stamp=float(stamps[i]) + 0.013, labels=labels[i],
                          T_world_camera=poses[i])
        w.write_odometry(odo_stamps, odo_poses)
        w.write_encoders(encoders)
        w.write_objects(objects)
    return {"calibration": calib, "stamps": stamps, "rgb": rgb, "depth": depth,
            "thermal": thermal, "labels": labels, "poses": poses, "odo_stamps": odo_stamps,
            "odo_poses": odo_poses, "encoders": encoders, "objects": objects}


@pytest.fixture
def synthetic(tmp_path: Path) -> tuple[Path, dict[str, Any]]:
    root = tmp_path / "sim_ds"
    return root, write_synthetic(root)


def replace_line(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


# ------------------------------------------------------------------ round trips


def test_round_trip_synthetic(synthetic: tuple[Path, dict[str, Any]]) -> None:
    """Scenario: 3 synthetic 64x48 frames with thermal, labels, ground truth, odometry,
    encoders and objects are written and read back; everything matches within the
    quantisation of each encoding."""
    root, src = synthetic
    r = DatasetReader(root)
    assert r.calibration == src["calibration"]
    assert len(r) == 3
    assert r.has_thermal and r.has_labels and r.has_groundtruth
    np.testing.assert_array_equal(r.stamps, src["stamps"])
    frames = list(r)
    for i, f in enumerate(frames):
        assert f.index == i and f.stamp == src["stamps"][i]
        assert f.rgb.dtype == np.uint8 and f.rgb.shape == (H, W, 3)
        np.testing.assert_array_equal(f.rgb, src["rgb"][i])  # channel order preserved
        assert f.depth_m.dtype == np.float32
        np.testing.assert_allclose(f.depth_m, src["depth"][i], atol=1.0 / 5000.0)
        assert np.all(f.depth_m[:5] == 0.0)
        assert f.labels is not None and f.labels.dtype == np.uint16
        np.testing.assert_array_equal(f.labels, src["labels"][i])
        assert f.thermal_k is not None and f.thermal_k.shape == (TH, TW)
        np.testing.assert_allclose(f.thermal_k, src["thermal"][i], atol=1.0 / 100.0)
        assert f.thermal_stamp == pytest.approx(src["stamps"][i] + 0.013, abs=1e-6)
        assert f.T_world_camera is not None
        np.testing.assert_allclose(f.T_world_camera, src["poses"][i], atol=1e-7)
    gt = r.groundtruth()
    assert gt is not None
    np.testing.assert_array_equal(gt[0], src["stamps"])
    np.testing.assert_allclose(gt[1], src["poses"], atol=1e-7)
    odo = r.odometry()
    assert odo is not None
    np.testing.assert_allclose(odo[0], src["odo_stamps"], atol=5e-7)
    np.testing.assert_allclose(odo[1], src["odo_poses"], atol=1e-7)
    enc = r.encoders()
    assert enc is not None
    np.testing.assert_allclose(enc, src["encoders"], atol=5e-7)
    np.testing.assert_array_equal(enc[:, 1:3], src["encoders"][:, 1:3])
    assert r.objects() == src["objects"]
    assert r.frame(-1).index == 2
    assert type(r.frame(np.int64(1)).index) is int
    with pytest.raises(IndexError):
        r.frame(3)


def test_calibration_toml_round_trip(tmp_path: Path) -> None:
    """Scenario: a full calibration (rgb, thermal, base, wheels) and an rgb-only one survive
    save/load exactly, and the written file is plain TOML with the documented tables."""
    rng = np.random.default_rng(3)
    full = make_calibration(rng)
    rgb_only = Calibration(rgb=TUM_CAMERAS["freiburg1"])
    for k, calib in enumerate((full, rgb_only)):
        path = tmp_path / f"c{k}.toml"
        save_calibration(path, calib)
        assert load_calibration(path) == calib
        doc = tomllib.loads(path.read_text())
        assert doc == calib.to_toml_dict()
        assert Calibration.from_toml_dict(doc, "x") == calib
    assert set(full.to_toml_dict()) == {"rgb", "thermal", "base"}
    assert set(rgb_only.to_toml_dict()) == {"rgb"}
    assert full != rgb_only
    # A rolling-shutter readout time is written only when set, and read back exactly.
    assert "readout_s" not in rgb_only.to_toml_dict()["rgb"]
    rolling = Calibration(rgb=TUM_CAMERAS["freiburg1"], rgb_readout_s=0.0175)
    save_calibration(tmp_path / "rs.toml", rolling)
    assert "readout_s = 0.0175\n" in (tmp_path / "rs.toml").read_text()
    assert load_calibration(tmp_path / "rs.toml") == rolling
    assert rolling != rgb_only


def test_written_twice_is_byte_identical(tmp_path: Path) -> None:
    """Scenario: the same synthetic input written to two folders gives the same file tree
    with byte-identical files."""
    a, b = tmp_path / "a", tmp_path / "b"
    write_synthetic(a, seed=11)
    write_synthetic(b, seed=11)
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert files_a == files_b
    assert Path("rgb") / f"{T0:.6f}.png" in files_a
    for rel in files_a:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel


def test_overwrite_replaces_only_dataset_files(tmp_path: Path) -> None:
    """Scenario: a 3-frame data set is overwritten by a 1-frame one; stale frames go,
    an unrelated file in the folder stays."""
    root = tmp_path / "ds"
    write_synthetic(root, n=3)
    (root / "notes.md").write_text("keep me")
    write_synthetic(root, n=1, overwrite=True)
    r = DatasetReader(root)
    assert len(r) == 1
    assert len(list((root / "rgb").iterdir())) == 1
    assert (root / "notes.md").read_text() == "keep me"


def test_close_on_exception_leaves_valid_dataset(tmp_path: Path) -> None:
    """Scenario: the with-block fails after two frames; the two frames form a readable
    data set, and writing after close is refused."""
    rng = np.random.default_rng(5)
    calib = Calibration(rgb=PinholeCamera(W, H, 50.0, 50.0, 31.5, 23.5))
    root = tmp_path / "ds"
    with pytest.raises(RuntimeError), DatasetWriter(root, calib) as w:
        for i in range(2):
            w.write_frame(T0 + i, rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                          np.ones((H, W)))
        raise RuntimeError("renderer crashed")
    r = DatasetReader(root)
    assert len(r) == 2 and not r.has_thermal and not r.has_labels and not r.has_groundtruth
    assert r.frame(0).T_world_camera is None and r.frame(0).thermal_k is None
    assert r.groundtruth() is None and r.odometry() is None and r.encoders() is None
    assert r.objects() is None
    with pytest.raises(DatasetError, match="closed"):
        w.write_frame(T0 + 5, np.zeros((H, W, 3), np.uint8), np.ones((H, W)))


# ------------------------------------------------------------------ encodings and time


def test_scaled_uint16_encoding_rules() -> None:
    """Scenario: depth values covering no-data markers, rounding and saturation encode as
    documented and decode back to metres."""
    depth_m = np.array([0.0, np.nan, -1.0, np.inf, 1.00009, 1.00011, 20.0, 0.00009])
    raw = encode_scaled_uint16(depth_m, 5000.0)
    assert raw.dtype == np.uint16
    np.testing.assert_array_equal(raw, [0, 0, 0, 0, 5000, 5001, 65535, 0])
    back = decode_scaled_uint16(raw, 5000.0)
    assert back.dtype == np.float32
    np.testing.assert_allclose(back, [0, 0, 0, 0, 1.0, 1.0002, 13.107, 0], atol=1e-6)


def test_associate_stamps_follows_tum_rule() -> None:
    """Scenario: closest pairs win, each stamp is used once, pairs beyond the window drop."""
    rgb = [0.0, 0.01, 0.1, 0.2]
    depth = [0.009, 0.105, 0.25]
    assert associate_stamps(rgb, depth, 0.02) == [(1, 0), (2, 1)]
    assert associate_stamps([], depth, 0.02) == []


def test_pose_at_interpolates_and_respects_gaps() -> None:
    """Scenario: a trajectory with a 0.01 s spacing and then a 0.3 s gap; queries inside,
    between, near the ends and in the gap."""
    rng = np.random.default_rng(1)
    stamps = np.array([0.0, 0.01, 0.31])
    T = np.stack([random_pose(rng) for _ in range(3)])
    np.testing.assert_array_equal(pose_at(stamps, T, 0.01), T[1])
    mid = pose_at(stamps, T, 0.005)
    assert mid is not None
    np.testing.assert_allclose(mid[:3, 3], (T[0, :3, 3] + T[1, :3, 3]) / 2, atol=1e-12)
    np.testing.assert_allclose(pose_at(stamps, T, 0.02), T[1])  # in the gap, near row 1
    assert pose_at(stamps, T, 0.15) is None  # gap of 0.3 s, no row within 0.02 s
    np.testing.assert_allclose(pose_at(stamps, T, 0.325), T[2])  # after the end, nearest
    assert pose_at(stamps, T, 0.35) is None
    assert pose_at(stamps, T, -0.05) is None
    assert pose_at(np.zeros(0), np.zeros((0, 4, 4)), 0.0) is None


def test_tum_camera_from_folder_name() -> None:
    """Scenario: folder names of TUM sequences select the published camera; others none."""
    assert tum_camera_for_folder("rgbd_dataset_freiburg2_desk") == TUM_CAMERAS["freiburg2"]
    assert tum_camera_for_folder("tum_fr1_rpy_s3_first100") == TUM_CAMERAS["freiburg1"]
    assert tum_camera_for_folder("FR3_office") == TUM_CAMERAS["freiburg3"]
    assert tum_camera_for_folder("fr1_vs_fr2") is None
    assert tum_camera_for_folder("frame1") is None
    assert tum_camera_for_folder("fr12") is None
    assert TUM_CAMERAS["freiburg3"].distortion == (0.0, 0.0, 0.0, 0.0, 0.0)


# ------------------------------------------------------------------ real TUM data


@needs_tum
def test_real_tum_folder_opens() -> None:
    """Scenario: the real TUM fr1 excerpt (100 frames, associations.txt, no calibration.toml)
    opens with the fr1 camera, every frame has ground truth and plausible depth."""
    r = DatasetReader(TUM_DIR)
    assert len(r) == 100
    assert r.calibration.rgb == TUM_CAMERAS["freiburg1"]
    assert r.calibration.depth_scale == 5000.0
    assert not r.has_thermal and not r.has_labels
    assert np.all(np.diff(r.stamps) > 0)
    for i in (0, 50, 99):
        f = r.frame(i)
        assert f.rgb.shape == (480, 640, 3) and f.rgb.dtype == np.uint8
        assert f.depth_m.shape == (480, 640)
        valid = f.depth_m[f.depth_m > 0]
        assert valid.size > 0.3 * f.depth_m.size
        assert 0.3 < float(np.median(valid)) < 5.0 and float(valid.max()) < 10.0
        assert f.depth_stamp is not None and abs(f.depth_stamp - f.stamp) < 0.02
    for f in r:
        assert f.T_world_camera is not None
        np.testing.assert_allclose(f.T_world_camera[:3, :3] @ f.T_world_camera[:3, :3].T,
                                   np.eye(3), atol=1e-9)


@needs_tum
def test_real_tum_nearest_association_matches_associations_file(tmp_path: Path) -> None:
    """Scenario: the TUM excerpt without associations.txt (text files copied, image folders
    linked) is associated by nearest stamp and gives the same pairs as the file."""
    root = tmp_path / "rgbd_dataset_freiburg1_rpy"
    root.mkdir()
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        shutil.copy(TUM_DIR / name, root / name)
    for name in ("rgb", "depth"):
        os.symlink(TUM_DIR / name, root / name)
    with_file = DatasetReader(TUM_DIR)
    nearest = DatasetReader(root)
    np.testing.assert_array_equal(nearest.stamps, with_file.stamps)
    assert [nearest.frame(i).depth_stamp for i in (0, 99)] == \
        [with_file.frame(i).depth_stamp for i in (0, 99)]


# ------------------------------------------------------------------ malformed folders


def test_missing_folder(tmp_path: Path) -> None:
    """Scenario: the folder does not exist, or is a file."""
    with pytest.raises(DatasetError, match="not found"):
        DatasetReader(tmp_path / "nope")
    (tmp_path / "afile").write_text("x")
    with pytest.raises(DatasetError, match="not a folder"):
        DatasetReader(tmp_path / "afile")


@pytest.mark.parametrize("name", ["rgb.txt", "depth.txt"])
def test_missing_list_file(synthetic: tuple[Path, dict[str, Any]], name: str) -> None:
    """Scenario: rgb.txt or depth.txt was deleted."""
    root, _ = synthetic
    (root / name).unlink()
    with pytest.raises(DatasetError, match=f"missing {name}"):
        DatasetReader(root)


@pytest.mark.parametrize(
    ("name", "edit", "message"),
    [
        ("rgb.txt", lambda s: s + "1700000001.0 rgb/x.png extra\n", r"rgb\.txt:6: expected 2 columns"),
        ("rgb.txt", lambda s: s.replace(f"{T0 + 0.1:.6f} ", "abc ", 1),
         r"rgb\.txt:4: timestamp is not a number: 'abc'"),
        ("depth.txt", lambda s: s + f"{T0:.6f} depth/{T0:.6f}.png\n",
         r"depth\.txt:6: stamp .* is not after"),
        ("groundtruth.txt", lambda s: s + "1700000001.0 1 2 3 0 0 0\n",
         r"groundtruth\.txt:6: expected 8 columns"),
        ("groundtruth.txt", lambda s: s + "1700000001.0 1 2 3 0 0 0 0\n",
         r"groundtruth\.txt:6: bad pose"),
        ("encoders.txt", lambda s: s + "1700000001.0 1 2 nan\n",
         r"encoders\.txt:14: gyro_z_rad_s is not finite"),
        ("labels.txt", lambda s: s + "1700000001.000000 labels/x.png\n",
         r"labels\.txt:6: stamp .* is not an rgb\.txt stamp"),
        ("rgb.txt", lambda s: s + "1700000001.0 /etc/passwd\n", "must be relative"),
    ],
)
def test_malformed_rows(synthetic: tuple[Path, dict[str, Any]], name: str, edit: Any,
                        message: str) -> None:
    """Scenario: one list or trajectory file gets a bad row; the error names file and line."""
    root, _ = synthetic
    path = root / name
    path.write_text(edit(path.read_text()))
    with pytest.raises(DatasetError, match=message):
        DatasetReader(root)


def test_referenced_image_missing(synthetic: tuple[Path, dict[str, Any]]) -> None:
    """Scenario: an rgb image listed in rgb.txt was deleted; opening the folder fails and
    names the list file, line and image."""
    root, _ = synthetic
    rel = f"rgb/{T0 + 0.1:.6f}.png"
    (root / rel).unlink()
    with pytest.raises(DatasetError, match=rf"rgb\.txt:4: {rel}"):
        DatasetReader(root)


@pytest.mark.parametrize("damage", ["garbage", "truncated", "empty"])
def test_corrupt_png(synthetic: tuple[Path, dict[str, Any]], damage: str) -> None:
    """Scenario: a depth PNG is overwritten with junk, cut short or emptied; the folder
    opens (images load lazily) and loading that frame names the file."""
    root, _ = synthetic
    path = root / "depth" / f"{T0 + 0.2:.6f}.png"
    data = path.read_bytes()
    path.write_bytes({"garbage": b"not a png" * 20, "truncated": data[:40], "empty": b""}[damage])
    r = DatasetReader(root)
    r.frame(0)
    with pytest.raises(DatasetError, match=rf"{path.name}: not a readable image"):
        r.frame(2)


def test_image_of_wrong_kind(synthetic: tuple[Path, dict[str, Any]]) -> None:
    """Scenario: an 8-bit colour image sits where a depth image belongs, and an rgb image
    has the wrong size for the calibration."""
    root, _ = synthetic
    shutil.copy(root / "rgb" / f"{T0:.6f}.png", root / "depth" / f"{T0:.6f}.png")
    r = DatasetReader(root)
    with pytest.raises(DatasetError, match="expected a 16-bit single-channel image"):
        r.frame(0)
    shutil.copy(root / "thermal" / f"{T0 + 0.113:.6f}.png", root / "rgb" / f"{T0 + 0.1:.6f}.png")
    with pytest.raises(DatasetError, match="8-bit colour"):
        r.frame(1)


def test_corrupt_objects_json(synthetic: tuple[Path, dict[str, Any]]) -> None:
    """Scenario: objects.json is not JSON, then is a JSON list."""
    root, _ = synthetic
    (root / "objects.json").write_text('{"world": \n  oops}')
    r = DatasetReader(root)
    with pytest.raises(DatasetError, match=r"objects\.json:2: not valid JSON"):
        r.objects()
    (root / "objects.json").write_text("[1, 2]")
    with pytest.raises(DatasetError, match="expected a JSON object"):
        r.objects()


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("fx = 50.5\n", "", r"\[rgb\]: missing key\(s\) fx"),
        ("fx = 50.5", 'fx = "fifty"', r"\[rgb\] fx: expected a finite number, got 'fifty'"),
        ("width = 64", "width = 64.0", r"\[rgb\] width: expected an integer"),
        ("distortion = [", "distortion = [1.0, ", r"\[rgb\] distortion: expected an array of 5"),
        ("fx = 50.5", "fx = -50.5", r"\[rgb\]: camera: focal lengths must be positive"),
        ("fx = 50.5", "fxx = 50.5", r"\[rgb\]: unknown key\(s\) fxx"),
        ("T_base_rgb = [\n    [", "T_base_rgb = [\n    [2.0, 0.0, 0.0, 0.0], [",
         r"\[base\] T_base_rgb: expected a 4x4 matrix"),
        ("ticks_per_mm = 11.7", "ticks_per_mm = 0.0", r"ticks_per_mm must be a positive"),
        ("fx = 50.5", "fx = 50.5\nreadout_s = -0.01", r"\[rgb\] readout_s\) must be in \[0, 0.1\]"),
        ("fx = 50.5", "fx = 50.5\nreadout_s = 0.5", r"\[rgb\] readout_s\) must be in \[0, 0.1\]"),
        ("fx = 50.5", 'fx = 50.5\nreadout_s = "20ms"', r"\[rgb\] readout_s: expected a finite number"),
        ("[rgb]", "[rgb\n", "malformed TOML"),
    ],
)
def test_bad_calibration_toml(synthetic: tuple[Path, dict[str, Any]], old: str, new: str,
                              message: str) -> None:
    """Scenario: calibration.toml has a missing key, a wrong type, a bad value, a typo or
    broken syntax; the error names calibration.toml and the key."""
    root, _ = synthetic
    replace_line(root / "calibration.toml", old, new)
    with pytest.raises(DatasetError, match=message) as info:
        DatasetReader(root)
    assert "calibration.toml" in str(info.value)


def test_non_rigid_transform_in_calibration(synthetic: tuple[Path, dict[str, Any]]) -> None:
    """Scenario: T_base_rgb's rotation block is scaled by 2, so it is not a rigid transform."""
    root, _ = synthetic
    path = root / "calibration.toml"
    doc = tomllib.loads(path.read_text())
    T = np.array(doc["base"]["T_base_rgb"])
    T[:3, :3] *= 2.0
    doc["base"]["T_base_rgb"] = T.tolist()
    path.write_text(tomli_w.dumps(doc))
    with pytest.raises(DatasetError, match=r"calibration\.toml: \[base\] T_base_rgb: not a rigid"):
        DatasetReader(root)


def test_unknown_camera_without_calibration(synthetic: tuple[Path, dict[str, Any]]) -> None:
    """Scenario: a folder whose name names no TUM camera has no calibration.toml; the error
    says both ways to fix it. Renamed to a freiburg3 name, it opens with that camera."""
    root, _ = synthetic
    for name in ("calibration.toml", "thermal.txt"):
        (root / name).unlink()
    with pytest.raises(DatasetError, match=r"calibration\.toml") as info:
        DatasetReader(root)
    assert "freiburg1" in str(info.value) and "fr1" in str(info.value)
    renamed = root.rename(root.parent / "rgbd_dataset_freiburg3_sim")
    with pytest.raises(DatasetError, match="calibration says 640x480"):
        DatasetReader(renamed).frame(0)  # the synthetic 64x48 images do not fit fr3's camera
    assert DatasetReader(renamed).calibration.rgb == TUM_CAMERAS["freiburg3"]


def test_thermal_without_thermal_calibration(synthetic: tuple[Path, dict[str, Any]]) -> None:
    """Scenario: thermal.txt is present but calibration.toml lost its [thermal] table."""
    root, src = synthetic
    c = src["calibration"]
    save_calibration(root / "calibration.toml", Calibration(rgb=c.rgb, T_base_rgb=c.T_base_rgb))
    with pytest.raises(DatasetError, match="no \\[thermal\\] table"):
        DatasetReader(root)


# ------------------------------------------------------------------ writer refusals


def test_writer_refuses_non_empty_folder(tmp_path: Path) -> None:
    """Scenario: the target folder holds a file; the writer refuses without overwrite and
    leaves the file alone."""
    root = tmp_path / "ds"
    root.mkdir()
    (root / "precious.txt").write_text("x")
    with pytest.raises(DatasetError, match=r"not empty.*overwrite=True"):
        DatasetWriter(root, Calibration(rgb=TUM_CAMERAS["freiburg1"]))
    assert sorted(p.name for p in root.iterdir()) == ["precious.txt"]


def test_writer_refuses_unwritable_folder(tmp_path: Path) -> None:
    """Scenario: the target lies under a regular file, or is a regular file."""
    (tmp_path / "afile").write_text("x")
    calib = Calibration(rgb=TUM_CAMERAS["freiburg1"])
    with pytest.raises(DatasetError, match="cannot create data-set folder"):
        DatasetWriter(tmp_path / "afile" / "sub", calib)
    with pytest.raises(DatasetError, match="is a file"):
        DatasetWriter(tmp_path / "afile", calib)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"stamp": T0 - 1.0}, "not after the previous frame"),
        ({"stamp": T0 + 1e-7}, "not after the previous frame"),
        ({"stamp": float("nan")}, "must be finite"),
        ({"rgb": np.zeros((H, W, 3), np.float32)}, r"rgb must be uint8 \(48, 64, 3\)"),
        ({"rgb": np.zeros((W, H, 3), np.uint8)}, "rgb must be uint8"),
        ({"depth_m": np.zeros((H, W, 1))}, r"depth_m must be numeric \(48, 64\)"),
        ({"thermal_k": np.zeros((H, W))}, r"thermal_k must be numeric \(24, 32\)"),
        ({"thermal_k": np.zeros((TH, TW)), "thermal_stamp": T0 + 1.05},
         "not within 0.04 s"),
        ({"thermal_stamp": T0 + 1.0}, "thermal_stamp given without thermal_k"),
        ({"labels": np.zeros((H, W), np.float32)}, "labels must be integer"),
        ({"labels": np.full((H, W), 70000, np.int64)}, r"labels must lie in 0\.\.65535"),
        ({"T_world_camera": 2.0 * np.eye(4)}, "T_world_camera"),
    ],
)
def test_writer_rejects_bad_frames(tmp_path: Path, kwargs: dict[str, Any], message: str) -> None:
    """Scenario: after one good frame, a frame with one bad argument is refused and
    nothing of it is written."""
    rng = np.random.default_rng(9)
    root = tmp_path / "ds"
    w = DatasetWriter(root, make_calibration(rng))
    good: dict[str, Any] = {"stamp": T0, "rgb": np.zeros((H, W, 3), np.uint8),
                            "depth_m": np.ones((H, W))}
    w.write_frame(**good)
    files_before = sorted(root.rglob("*"))
    args = {**good, "stamp": T0 + 1.0, **kwargs}
    with pytest.raises(DatasetError, match=message):
        w.write_frame(args.pop("stamp"), args.pop("rgb"), args.pop("depth_m"), **args)
    assert sorted(root.rglob("*")) == files_before
    w.close()
    assert len(DatasetReader(root)) == 1


def test_writer_rejects_bad_streams(tmp_path: Path) -> None:
    """Scenario: odometry, encoders and objects with wrong shapes, order or content."""
    rng = np.random.default_rng(2)
    calib = Calibration(rgb=TUM_CAMERAS["freiburg1"])
    with DatasetWriter(tmp_path / "ds", calib) as w:
        poses = np.stack([random_pose(rng) for _ in range(3)])
        with pytest.raises(DatasetError, match=r"expected stamps \(N,\)"):
            w.write_odometry([0.0, 1.0], poses)
        with pytest.raises(DatasetError, match="stamps must increase"):
            w.write_odometry([0.0, 1.0, 1.0], poses)
        with pytest.raises(DatasetError, match=r"T_odom_base\[1\]"):
            w.write_odometry([0.0, 1.0, 2.0], poses * np.array([1.0, 3.0, 1.0])[:, None, None])
        with pytest.raises(DatasetError, match=r"expected \(K, 4\)"):
            w.write_encoders(np.zeros((3, 3)))
        with pytest.raises(DatasetError, match="integer counts"):
            w.write_encoders([[0.0, 1.5, 2.0, 0.0], [1.0, 2.0, 3.0, 0.0]])
        with pytest.raises(DatasetError, match="cannot encode as JSON"):
            w.write_objects({"objects": [{"size": float("nan")}]})
        with pytest.raises(DatasetError, match="expected a dict"):
            not_a_dict: Any = [1, 2]
            w.write_objects(not_a_dict)
        w.write_objects({"objects": [{"T_world_object": np.eye(4), "id": np.int64(3)}]})
        w.write_frame(T0, np.zeros((480, 640, 3), np.uint8), np.zeros((480, 640)))
    doc = DatasetReader(tmp_path / "ds").objects()
    assert doc == {"objects": [{"T_world_object": np.eye(4).tolist(), "id": 3}]}


def test_calibration_validates_direct_construction() -> None:
    """Scenario: Calibration built in code with inconsistent or invalid fields."""
    cam = TUM_CAMERAS["freiburg1"]
    with pytest.raises(DatasetError, match="together"):
        Calibration(rgb=cam, thermal=cam)
    with pytest.raises(DatasetError, match="depth_scale"):
        Calibration(rgb=cam, depth_scale=0.0)
    with pytest.raises(DatasetError, match="need T_base_rgb"):
        Calibration(rgb=cam, wheel_base_m=0.2)
    with pytest.raises(DatasetError, match="T_base_rgb"):
        Calibration(rgb=cam, T_base_rgb=np.zeros((4, 4)))
    c = Calibration(rgb=cam, T_base_rgb=np.eye(4))
    assert c.T_base_rgb is not None and not c.T_base_rgb.flags.writeable


# ------------------------------------------------------------------ association files, camera by name


def _no_calibration(root: Path) -> None:
    for name in ("calibration.toml", "thermal.txt", "associations.txt"):
        (root / name).unlink(missing_ok=True)


def _associations_text(root: Path, rows: list[int], *, depth_first: bool = False) -> str:
    def rows_of(name: str) -> list[list[str]]:
        return [line.split() for line in (root / name).read_text().splitlines() if not line.startswith("#")]

    rgb, depth = rows_of("rgb.txt"), rows_of("depth.txt")
    pairs = [(depth[i] + rgb[i]) if depth_first else (rgb[i] + depth[i]) for i in rows]
    return "".join(" ".join(p) + "\n" for p in pairs)


@pytest.mark.parametrize("name", ["associations.txt", "rgbd_assoc.txt", "assoc.txt"])
def test_tum_association_file_names(synthetic: tuple[Path, dict[str, Any]], name: str) -> None:
    """Scenario: an association file under each of TUM users' usual names pairs only the
    frames it lists (frames 0 and 2 of 3), where nearest stamps would pair all three."""
    root, data = synthetic
    (root / "associations.txt").unlink(missing_ok=True)
    assert len(DatasetReader(root)) == 3 and DatasetReader(root).associations is None
    (root / name).write_text("# rgb depth\n" + _associations_text(root, [0, 2]))
    r = DatasetReader(root)
    assert r.associations == root / name
    np.testing.assert_array_equal(r.stamps, data["stamps"][[0, 2]])
    np.testing.assert_array_equal(r.frame(1).rgb, data["rgb"][2])


def test_associations_option_file_and_column_order(synthetic: tuple[Path, dict[str, Any]],
                                                   tmp_path: Path) -> None:
    """Scenario: ``associations=FILE`` outside the folder wins over the folder's own file; a
    file written depth-first (``associate.py depth.txt rgb.txt``) is read the right way round;
    a missing file is a one-line error naming it."""
    root, data = synthetic
    (root / "associations.txt").write_text(_associations_text(root, [0, 1, 2]))
    outside = tmp_path / "mine.txt"
    outside.write_text(_associations_text(root, [1], depth_first=True))
    r = DatasetReader(root, associations=outside)
    assert r.associations == outside and len(r) == 1
    assert r.stamps[0] == pytest.approx(data["stamps"][1])
    np.testing.assert_allclose(r.frame(0).depth_m, data["depth"][1], atol=1e-3)
    with pytest.raises(DatasetError, match=r"association file not found: .*nope\.txt"):
        DatasetReader(root, associations=tmp_path / "nope.txt")


def test_camera_from_the_folders_own_name_not_a_links_target(synthetic: tuple[Path, dict[str, Any]]) -> None:
    """Scenario: a link named after a TUM sequence (fr2) pointing at a folder named after
    another (fr1) opens with the link's camera; a link whose name names no camera falls back
    to its target's; the folder itself keeps its own."""
    root, _ = synthetic
    _no_calibration(root)
    target = root.rename(root.parent / "rgbd_dataset_freiburg1_copy")
    link = root.parent / "rgbd_dataset_freiburg2_desk"
    link.symlink_to(target, target_is_directory=True)
    plain = root.parent / "latest"
    plain.symlink_to(target, target_is_directory=True)
    assert DatasetReader(link).calibration.rgb == TUM_CAMERAS["freiburg2"]
    assert DatasetReader(plain).calibration.rgb == TUM_CAMERAS["freiburg1"]
    assert DatasetReader(target).calibration.rgb == TUM_CAMERAS["freiburg1"]


def test_readout_model_says_where_it_comes_from(synthetic: tuple[Path, dict[str, Any]]) -> None:
    """Scenario: the readout time comes from ``[rgb] readout_s`` when given (0 included), else
    from the named sensor's default (a TUM folder: the Kinect), else it is a guess of 0 that
    says so; an unknown sensor name is an error listing the known ones."""
    root, _ = synthetic
    _no_calibration(root)
    tum = DatasetReader(root.rename(root.parent / "rgbd_dataset_freiburg1_rpy")).calibration
    assert tum.rgb_sensor == "kinect_v1" and tum.rgb_readout_s is None
    assert tum.readout.readout_s > 0 and "Kinect" in tum.readout.source and not tum.readout.assumed
    cam = TUM_CAMERAS["freiburg1"]
    given = Calibration(rgb=cam, rgb_readout_s=0.0, rgb_sensor="kinect_v1").readout
    assert given.readout_s == 0.0 and "readout_s" in given.source and not given.assumed
    nothing = Calibration(rgb=cam).readout
    assert nothing.readout_s == 0.0 and nothing.assumed and "calibrate-readout" in nothing.source
    unknown_time = Calibration(rgb=cam, rgb_sensor="azure_kinect").readout
    assert unknown_time.assumed and "rolling shutter" in unknown_time.source
    with pytest.raises(DatasetError, match="'kinect9' is not a known sensor; known: kinect_v1"):
        Calibration(rgb=cam, rgb_sensor="kinect9")


def test_calibration_toml_sensor_round_trip(tmp_path: Path) -> None:
    """Scenario: ``[rgb] sensor`` and an explicit ``readout_s = 0`` survive a save and load; a
    non-string sensor is an error naming the key."""
    calib = Calibration(rgb=TUM_CAMERAS["freiburg1"], rgb_readout_s=0.0, rgb_sensor="realsense_d455")
    save_calibration(tmp_path / "c.toml", calib)
    assert load_calibration(tmp_path / "c.toml") == calib
    text = (tmp_path / "c.toml").read_text().replace('sensor = "realsense_d455"', "sensor = 3")
    (tmp_path / "c.toml").write_text(text)
    with pytest.raises(DatasetError, match=r"\[rgb\] sensor: expected a string"):
        load_calibration(tmp_path / "c.toml")
