"""``deploy/backend.toml`` holds the back-end's defaults; bad keys and values are named."""

from __future__ import annotations

from pathlib import Path

import pytest

from wardmap.server.backend.core import BackendConfig
from wardmap.shared.config import load_config
from wardmap.shared.errors import ConfigError

DEPLOY = Path(__file__).resolve().parents[3] / "deploy" / "backend.toml"


def test_the_example_config_equals_the_defaults() -> None:
    assert load_config(BackendConfig, DEPLOY, section="backend") == BackendConfig()


@pytest.mark.parametrize(("text", "named"), [
    ("[backend]\ncandidates = 0\n", "candidates"),
    ("[backend]\nmin_similarity = 1.5\n", "min_similarity"),
    ("[backend]\nanchor_votes = 0\n", "anchor_votes"),
    ("[backend]\nanchor_span_deg = -1.0\n", "anchor_span_deg"),
    ("[backend]\nloops = 3\n", "loops"),
    ("[backend.ferns]\nblocks = 0\n", "blocks"),
    ("[backend.graph]\nrobust_kernel = \"tukey\"\n", "robust_kernel"),
])
def test_bad_settings_are_named(tmp_path: Path, text: str, named: str) -> None:
    path = tmp_path / "server.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=named):
        load_config(BackendConfig, path, section="backend")
