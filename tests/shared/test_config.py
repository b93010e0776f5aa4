"""TOML config into frozen dataclasses: defaults, nesting, and every error path."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from wardmap.shared.config import from_mapping, load_config, to_mapping
from wardmap.shared.errors import ConfigError


@dataclass(frozen=True)
class Inner:
    n: int = 3
    mode: str = "a"


@dataclass(frozen=True)
class Outer:
    rate_hz: float = 10.0
    name: str = "x"
    flags: tuple[int, ...] = ()
    inner: Inner = field(default_factory=Inner)
    path: Path | None = None

    def __post_init__(self) -> None:
        if self.rate_hz <= 0:
            raise ValueError("rate_hz must be positive")


def test_defaults_nesting_and_round_trip(tmp_path: Path) -> None:
    """A file overriding some keys gives a frozen object; to_mapping round-trips it."""
    p = tmp_path / "c.toml"
    p.write_text('rate_hz = 5\nflags = [1, 2]\npath = "/tmp/x"\n[inner]\nn = 7\n')
    cfg = load_config(Outer, p)
    assert cfg.rate_hz == 5.0 and isinstance(cfg.rate_hz, float)
    assert cfg.inner == Inner(7, "a") and cfg.flags == (1, 2) and cfg.path == Path("/tmp/x")
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.rate_hz = 1.0  # type: ignore[misc]
    assert from_mapping(Outer, to_mapping(cfg)) == cfg
    assert load_config(Outer, None) == Outer()


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("rate_hz = 'fast'", "rate_hz: expected a number"),
        ("rat_hz = 3", "unknown key"),
        ("[inner]\nn = 1.5", "inner.n: expected an integer"),
        ("[inner]\nbogus = 1", r"\[inner\] unknown key"),
        ("inner = 3", "inner: expected a table"),
        ("rate_hz = -1", "rate_hz must be positive"),
        ("rate_hz = = 3", "malformed TOML"),
        ("flags = [1, 'a']", r"flags\[1\]"),
    ],
)
def test_bad_values_name_the_key(tmp_path: Path, text: str, match: str) -> None:
    """Each mistake raises ConfigError naming the key and the problem."""
    p = tmp_path / "c.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_config(Outer, p)


def test_missing_file(tmp_path: Path) -> None:
    """A missing config file is a ConfigError naming the path."""
    with pytest.raises(ConfigError, match="not found"):
        load_config(Outer, tmp_path / "nope.toml")
