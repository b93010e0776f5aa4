"""``wardmap map``: a run writes landmarks.json; bad input gives one clear line and exit code 1."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from procs import one_line_error, wardmap

from wardmap.sim.runner import generate

TUM = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tum_fr1_rpy_s3_first100"




@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "ward_chairs_s0"
    generate("ward_chairs", 0, out, frames=6)
    return out


def test_map_writes_landmarks(small: Path, tmp_path: Path) -> None:
    """A run on six frames (every frame a keyframe) prints a JSON summary and writes the file."""
    cfg = tmp_path / "c.toml"
    cfg.write_text("[map]\nkeyframe_min_translation_m = 0.0\nkeyframe_min_rotation_deg = 0.0\n")
    p = wardmap("map", str(small), "--out", str(tmp_path / "o"), "--config", str(cfg),
                "--association", "nearest")
    assert p.returncode == 0, p.stderr
    summary = json.loads(p.stdout.strip().splitlines()[-1])
    doc = json.loads((tmp_path / "o" / "landmarks.json").read_text())
    assert summary["method"] == doc["method"] == "nearest"
    assert summary["landmarks"] == len(doc["landmarks"]) > 0
    assert summary["keyframes"] == 6
    score = summary["score"]  # oracle measurements of a simulated data set: scored
    assert 0.0 < score["accuracy"] <= 1.0 and 0.0 < score["completeness"] <= 1.0
    assert min(score["accuracy"], score["completeness"]) <= score["f_measure"] <= max(score["accuracy"],
                                                                                   score["completeness"])
    assert score["objects"] + score["unconfirmed"] == summary["landmarks"] and score["gt_objects"] > 0


def test_missing_dataset(tmp_path: Path) -> None:
    one_line_error(wardmap("map", str(tmp_path / "nope"), "--out", str(tmp_path / "o")), "not found", "map")


def test_bad_config_key(small: Path, tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text("[association.hdp]\nsigma = 2\n")
    one_line_error(wardmap("map", str(small), "--out", str(tmp_path / "o"), "--config", str(cfg)),
                   "unknown key", "map")


def test_oracle_needs_simulator_labels(tmp_path: Path) -> None:
    """A real TUM folder has no labels: --measurements oracle is refused with a clear line."""
    if not TUM.is_dir():
        pytest.skip(f"{TUM} absent")
    one_line_error(wardmap("map", str(TUM), "--out", str(tmp_path / "o")), "needs labels", "map")


def test_poses_once_per_dataset(small: Path, tmp_path: Path) -> None:
    traj = tmp_path / "t.txt"
    traj.write_text("0 0 0 0 0 0 0 1\n")
    p = wardmap("map", str(small), str(small), "--out", str(tmp_path / "o"), "--poses", str(traj))
    one_line_error(p, "one trajectory per data set", "map")


def test_model_measurements_without_the_model(small: Path, tmp_path: Path) -> None:
    """--measurements model before a model is installed: one line saying so."""
    from wardmap.server.perception.models import packaged_model_path

    if packaged_model_path().is_file():
        pytest.skip("the packaged model is installed")
    p = wardmap("map", str(small), "--out", str(tmp_path / "o"), "--measurements", "model")
    one_line_error(p, "not installed", "map")
