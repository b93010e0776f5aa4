"""The ``wardmap`` command: bad input gives one clear line and exit code 1, never a traceback."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from procs import one_line_error, wardmap

TUM = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tum_fr1_rpy_s3_first100"




def test_sim_list_names_every_scenario() -> None:
    """``wardmap sim --list`` prints each scenario with a description."""
    p = wardmap("sim", "--list")
    assert p.returncode == 0
    for name in (
        "aisle_slow_1",
        "aisle_quick_3",
        "ward_chairs",
        "hospital_loop",
        "walking_staff",
        "dark_corridor",
        "two_robots",
    ):
        assert name in p.stdout


def test_unknown_scenario(tmp_path: Path) -> None:
    """A misspelt scenario: one line naming the known scenarios, exit 1."""
    one_line_error(
        wardmap("sim", "--scenario", "hospital_lop", "--out", str(tmp_path / "o")), "unknown scenario"
    )


def test_unwritable_output_folder(tmp_path: Path) -> None:
    """An output path below a regular file cannot be created: one line, exit 1."""
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    p = wardmap("sim", "--scenario", "aisle_slow_1", "--out", str(blocker / "sub"), "--frames", "1")
    one_line_error(p, "wardmap sim: error:")


def test_non_empty_output_folder_is_refused(tmp_path: Path) -> None:
    """Existing data are never overwritten silently."""
    (tmp_path / "keep.txt").write_text("precious")
    p = wardmap("sim", "--scenario", "aisle_slow_1", "--out", str(tmp_path), "--frames", "1")
    one_line_error(p, "wardmap sim: error:")
    assert (tmp_path / "keep.txt").read_text() == "precious"


def test_sim_then_dataset_info(tmp_path: Path) -> None:
    """A two-frame simulation, then ``dataset info --json`` reads it back."""
    out = tmp_path / "clip"
    p = wardmap("sim", "--scenario", "dark_corridor", "--seed", "2", "--out", str(out), "--frames", "2")
    assert p.returncode == 0, p.stderr
    info = wardmap("dataset", "info", str(out), "--json", "--check-images")
    assert info.returncode == 0, info.stderr
    summary = json.loads(info.stdout)
    assert summary["frames"] == 2 and summary["thermal"] and summary["labels"]
    assert summary["groundtruth_poses"] == 2 and summary["objects"] > 10
    # The simulator renders a global shutter and says so in its calibration.
    assert summary["rgb_readout_s"] == 0.0 and "[rgb] readout_s" in summary["rgb_readout_source"]


@pytest.mark.parametrize(
    ("setup", "needle"),
    [
        (lambda d: None, "wardmap dataset: error:"),
        (lambda d: (d / "rgb.txt").write_text("# hdr\n1.0 rgb/1.png\n"), "wardmap dataset: error:"),
        (
            lambda d: (
                (d / "rgb.txt").write_text("1.0 rgb/1.png extra junk\nnot-a-number x\n"),
                (d / "depth.txt").write_text("1.0 depth/1.png\n"),
            ),
            "wardmap dataset: error:",
        ),
    ],
    ids=["empty-folder", "missing-depth-list", "malformed-rows"],
)
def test_malformed_tum_folder(tmp_path: Path, setup: object, needle: str) -> None:
    """A TUM-like folder with missing or malformed files: one line, exit 1."""
    d = tmp_path / "rgbd_dataset_freiburg1_bad"
    d.mkdir()
    setup(d)  # type: ignore[operator]
    one_line_error(wardmap("dataset", "info", str(d)), needle)


def test_missing_dataset_folder(tmp_path: Path) -> None:
    """A path that does not exist: one line, exit 1."""
    one_line_error(wardmap("dataset", "info", str(tmp_path / "nope")), "wardmap dataset: error:")


@pytest.mark.skipif(not TUM.is_dir(), reason="../shared/data/tum_fr1_rpy_s3_first100 not present")
def test_dataset_info_on_real_tum_folder() -> None:
    """The real TUM sample opens unchanged (camera chosen from the folder name)."""
    p = wardmap("dataset", "info", str(TUM), "--json")
    assert p.returncode == 0, p.stderr
    summary = json.loads(p.stdout)
    assert summary["frames"] == 100 and "fx=517.3" in summary["rgb_camera"]
    assert summary["associations"].endswith("associations.txt")
    assert summary["rgb_readout_s"] > 0 and "Kinect v1" in summary["rgb_readout_source"]


@pytest.mark.skipif(not TUM.is_dir(), reason="../shared/data/tum_fr1_rpy_s3_first100 not present")
def test_track_names_its_readout_model_and_reads_association_files(tmp_path: Path) -> None:
    """Scenario: ``track`` on a link to the TUM sample named after no camera, with the sample's
    association file given by ``--associations``: it says which readout time it uses and why
    (the Kinect default, from the link's target name). ``--associations`` on a simulated robot
    is a one-line error."""
    link = tmp_path / "mine"
    link.symlink_to(TUM, target_is_directory=True)
    assoc = tmp_path / "pairs.txt"
    assoc.write_text("".join((TUM / "associations.txt").read_text().splitlines(keepends=True)[:5]))
    out = tmp_path / "traj.txt"
    p = wardmap("track", str(link), "--associations", str(assoc), "--out", str(out), "--max-frames", "3")
    assert p.returncode == 0, p.stderr
    assert "rolling-shutter readout: 26.6 ms (default for Kinect v1" in p.stderr
    summary = json.loads(p.stdout.splitlines()[-1])
    assert summary["frames"] == 3 and not summary["readout"]["assumed"]
    one_line_error(
        wardmap("track", "--source", "sim:aisle_slow_1", "--associations", str(assoc), "--out", str(out)),
        "--associations is for a data-set folder",
    )


TRAJ = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tum_trajectories"


@pytest.mark.skipif(not TRAJ.is_dir(), reason="../shared/data/tum_trajectories absent")
def test_eval_ate_on_reference_trajectories() -> None:
    """``wardmap eval ate`` scores RGBD-SLAM on fr1/xyz: about 1.3 cm (TUM's published order)."""
    p = wardmap(
        "eval",
        "ate",
        str(TRAJ / "freiburg1_xyz-rgbdslam.txt"),
        "--reference",
        str(TRAJ / "freiburg1_xyz-groundtruth.txt"),
    )
    assert p.returncode == 0, p.stderr
    r = json.loads(p.stdout)
    assert 0.005 < r["ate_rmse_m"] < 0.03 and r["pairs"] > 700


def test_eval_ate_bad_input(tmp_path: Path) -> None:
    """Missing or malformed trajectory files: one line, exit 1."""
    one_line_error(
        wardmap("eval", "ate", str(tmp_path / "nope.txt"), "--reference", str(tmp_path / "x")),
        "wardmap eval: error:",
    )
    bad = tmp_path / "bad.txt"
    bad.write_text("1.0 0 0 0 0 0 0\n")  # 7 columns: missing qw
    one_line_error(wardmap("eval", "ate", str(bad), "--reference", str(bad)), "wardmap eval: error:")


@pytest.mark.parametrize("pose", ["1,2", "a,b,c", "1,2,nan"])
def test_edge_bad_map_pose(tmp_path: Path, pose: str) -> None:
    """A malformed --map-pose fails before anything connects or an outbox is made."""
    p = wardmap("edge", "--robot", "r1", "--source", "sim:aisle_slow_1", "--connect", "tcp/127.0.0.1:7447",
                "--outbox", str(tmp_path / "ob"), "--map-pose", pose)
    one_line_error(p, "--map-pose")
    assert not (tmp_path / "ob").exists()


def test_map_pose_is_a_planar_pose() -> None:
    import numpy as np

    from wardmap.cli.edge_cmd import parse_map_pose

    T = parse_map_pose("2.5,-1,90")
    np.testing.assert_allclose(T[:3, 3], [2.5, -1.0, 0.0])
    np.testing.assert_allclose(T[:3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("option", ["--site-coco", "--site-masks", "--site-negatives"])
def test_train_seg_names_a_missing_site_path(tmp_path: Path, option: str) -> None:
    """A mistyped site path is one line naming it, before anything is rendered or trained."""
    p = wardmap("train-seg", "--out", str(tmp_path / "m.onnx"), option, str(tmp_path / "nope"))
    one_line_error(p, str(tmp_path / "nope"), "train-seg")
    assert "not found" in p.stderr and not (tmp_path / "m.onnx").exists()


def test_cameras_that_are_not_there_or_not_offered_are_one_line(tmp_path: Path) -> None:
    """``--source orbbec`` with no camera (or without the SDK's bindings), ``orbbec:x`` and
    ``k4a``: one line each, exit 1."""
    out = str(tmp_path / "traj.txt")
    try:
        import pyorbbecsdk  # noqa: F401

        why = "no Orbbec camera is connected"
    except ImportError:
        why = "pip install"
    one_line_error(wardmap("track", "--source", "orbbec", "--out", out), why)
    one_line_error(wardmap("track", "--source", "orbbec:front", "--out", out), "orbbec:N")
    one_line_error(wardmap("track", "--source", "k4a", "--out", out), "Azure Kinect SDK")
