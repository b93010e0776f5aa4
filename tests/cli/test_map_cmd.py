"""``wardmap map``: a run writes landmarks.json; bad input gives one clear line and exit code 1."""

from __future__ import annotations

import json
import subprocess
import sys
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


# ``python -c`` program: ``wardmap ARGV[2:]`` with the packaged model looked up at ARGV[1].
_WITHOUT_MODEL = """
import sys
from pathlib import Path

import wardmap.server.perception.models as models

if not callable(getattr(models, "packaged_model_path", None)):
    sys.exit("test seam gone: wardmap.server.perception.models.packaged_model_path")
missing = Path(sys.argv.pop(1))
models.packaged_model_path = lambda: missing
from wardmap.cli.main import main

sys.exit(main(sys.argv[1:]))
"""


def test_model_measurements_without_the_model(small: Path, tmp_path: Path) -> None:
    """--measurements model before a model is installed: one line saying so. The child process
    looks for the packaged model at a path that does not exist (the real one is installed)."""
    missing = tmp_path / "models" / "hospital_seg.onnx"
    p = subprocess.run(
        [sys.executable, "-c", _WITHOUT_MODEL, str(missing),
         "map", str(small), "--out", str(tmp_path / "o"), "--measurements", "model"],
        capture_output=True, text=True, timeout=300,
    )
    one_line_error(p, "not installed", "map")
    assert str(missing) in p.stderr  # the message names where it looked


YOLOX = TUM.parents[1] / "models" / "yolox_nano.onnx"


@pytest.mark.parametrize("spec", ["nope.onnx", "model:nope.onnx", "yolox:nope.onnx"])
def test_measurements_spec_with_a_missing_file(small: Path, tmp_path: Path, spec: str) -> None:
    """Every segmenter spec that names a file that is not there: one line naming the spec."""
    p = wardmap("map", str(small), "--out", str(tmp_path / "o"), "--measurements", spec)
    one_line_error(p, "not found", "map")
    assert f"--measurements {spec}" in p.stderr
    assert not (tmp_path / "o").exists()


def test_measurements_spec_that_is_not_a_model(small: Path, tmp_path: Path) -> None:
    """A file that is no ONNX model (here a text file) is refused at start with one line."""
    bad = tmp_path / "bad.onnx"
    bad.write_text("not a model\n")
    one_line_error(wardmap("map", str(small), "--out", str(tmp_path / "o"), "--measurements", str(bad)),
                   "not a readable ONNX model", "map")


def test_yolox_measurements_on_the_tum_excerpt(tmp_path: Path) -> None:
    """``--measurements yolox:PATH`` maps a real TUM recording (ground-truth poses): the office's
    monitor is found, and no class COCO cannot give (door, wheelchair, ...) appears."""
    if not (TUM.is_dir() and YOLOX.is_file()):
        pytest.skip(f"{TUM} or {YOLOX} absent")
    p = wardmap("map", str(TUM), "--out", str(tmp_path / "o"), "--measurements", f"yolox:{YOLOX}",
                "--association", "nearest")
    assert p.returncode == 0, p.stderr
    doc = json.loads((tmp_path / "o" / "landmarks.json").read_text())
    assert doc["measurements"] == f"yolox:{YOLOX}"
    classes = {lm["class"] for lm in doc["landmarks"]}
    assert "wall_monitor" in classes
    assert not classes & {"door", "wheelchair", "cart", "iv_pole", "temperature_gun", "cabinet", "bed"}
