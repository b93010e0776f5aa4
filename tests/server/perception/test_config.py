"""Perception settings (``server/perception/config.py``): the example file, validation, the
detector's measurement settings."""

from __future__ import annotations

from pathlib import Path

import pytest

from wardmap.server.perception.config import PerceptionConfig, load_perception_config, measure_config_for
from wardmap.shared.config import to_mapping
from wardmap.shared.errors import ConfigError

REPO = Path(__file__).resolve().parents[3]


def test_perception_config_toml(tmp_path: Path) -> None:
    """deploy/perception.toml holds the defaults; unknown keys and bad values are named."""
    assert to_mapping(load_perception_config(REPO / "deploy" / "perception.toml")) == to_mapping(
        PerceptionConfig()
    )
    bad = tmp_path / "p.toml"
    for text, named in (
        ("[perception.measure]\nmin_pointz = 3\n", "min_pointz"),
        ("[perception]\nthreads = 0\n", "threads"),
        ("[perception]\ndetector_cluster_gap_m = -1\n", "detector_cluster_gap_m"),
        ("[perception]\nsplit_width_m = 0\n", "split_width_m"),
        ('[perception]\nsplit_width_m = [["door", 0]]\n', "split_width_m of 'door'"),
        ('[perception]\nstack_gap_m = [["iv_pole"]]\n', "stack_gap_m"),
        ("[perception]\nmin_region_confidence = 1.5\n", "min_region_confidence"),
    ):
        bad.write_text(text)
        with pytest.raises(ConfigError, match=named):
            load_perception_config(bad)
    bad.write_text('[perception]\nsegmenter = "yolox:x.onnx"\n[perception.measure]\nmin_points = 80\n')
    cfg = load_perception_config(bad)
    assert cfg.segmenter == "yolox:x.onnx" and cfg.measure.min_points == 80
    # A yolox: detector's measurements keep their largest 3D piece by default; the network's do not;
    # an explicit [perception.measure] cluster_gap_m wins.
    assert measure_config_for(cfg, cfg.segmenter).cluster_gap_m == 0.05
    assert measure_config_for(cfg, "model").cluster_gap_m == 0.0
    bad.write_text('[perception]\nsegmenter = "yolox:x.onnx"\n[perception.measure]\ncluster_gap_m = 0.1\n')
    assert measure_config_for(load_perception_config(bad), "yolox:x.onnx").cluster_gap_m == 0.1
