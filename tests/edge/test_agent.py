"""The edge agent's configuration: the example file, validation of every budget setting."""

from __future__ import annotations

from pathlib import Path

import pytest

from wardmap.edge.agent import AgentConfig
from wardmap.shared.config import load_config
from wardmap.shared.errors import ConfigError


def test_example_config_matches_the_defaults() -> None:
    path = Path(__file__).resolve().parents[2] / "deploy" / "edge.toml"
    assert load_config(AgentConfig, path, section="agent") == AgentConfig()


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("depth_stride = 3", "depth_stride"),
        ("thermal_stride = 8", "thermal_stride"),
        ("thermal_every = -1", "thermal_every"),
        ("max_keypoints = -5", "max_keypoints"),
        ("thermal_unit_k = 0.0", "thermal_unit_k"),
        ("jpeg_quality = 0", "jpeg_quality"),
        ("label_threads = 0", "label_threads"),
        ("rate_hz = -1.0", "rate_hz"),
        ("jpg_quality = 80", "jpg_quality"),
    ],
)
def test_bad_agent_config_is_rejected(tmp_path: Path, text: str, needle: str) -> None:
    path = tmp_path / "edge.toml"
    path.write_text(f"[agent]\n{text}\n")
    with pytest.raises(ConfigError, match=needle):
        load_config(AgentConfig, path, section="agent")
