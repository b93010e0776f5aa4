"""Tests of wardmap.cli.zenoh_args: the ``[zenoh]`` TOML table under the ``--zenoh-config`` and
``--tls-*`` flags that ``wardmap router``, ``server`` and ``edge`` share."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from wardmap.cli.zenoh_args import add_zenoh_args, zenoh_options
from wardmap.shared.errors import ConfigError
from wardmap.shared.zenoh_config import ZenohOptions


def _parse(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_zenoh_args(p)
    return p.parse_args(argv)


def test_flags_override_the_toml_table_key_by_key(tmp_path: Path) -> None:
    """Each flag replaces its own key of ``[zenoh]``; keys without a flag keep the file's value;
    no file and no flag: nothing set."""
    toml = tmp_path / "edge.toml"
    toml.write_text('[agent]\nrate_hz = 5.0\n[zenoh]\ntls_ca = "/etc/wardmap/ca.crt"\n'
                    'tls_cert = "/etc/wardmap/r.crt"\ntls_key = "/etc/wardmap/r.key"\n')
    opts = zenoh_options(_parse("--tls-ca", "/site/ca.crt", "--zenoh-config", "z.json5"), str(toml))
    assert opts == ZenohOptions(config="z.json5", tls_ca="/site/ca.crt", tls_cert="/etc/wardmap/r.crt",
                                tls_key="/etc/wardmap/r.key")
    assert zenoh_options(_parse()) == ZenohOptions()


@pytest.mark.parametrize(
    ("table", "argv", "match"),
    [
        ('[zenoh]\ntls_crt = "x"\n', (), "unknown key"),
        ("", ("--tls-cert", "r.crt"), "go together"),
        ('[zenoh]\ntls_key = "r.key"\n', (), "go together"),
    ],
)
def test_bad_tables_and_flags_are_config_errors(tmp_path: Path, table: str, argv: tuple[str, ...],
                                                match: str) -> None:
    """A misspelt key, or a certificate without its key (from the file or the flags): ConfigError."""
    toml = tmp_path / "server.toml"
    toml.write_text(table)
    with pytest.raises(ConfigError, match=match):
        zenoh_options(_parse(*argv), str(toml))


@pytest.mark.parametrize("name", ["edge.toml", "server.toml"])
def test_the_commented_zenoh_table_of_the_deploy_files_loads(name: str, tmp_path: Path) -> None:
    """Uncommented, the ``[zenoh]`` example of ``deploy/NAME`` (up to its blank line) is a valid table."""
    text = (Path(__file__).resolve().parents[2] / "deploy" / name).read_text()
    table = text[text.index("# [zenoh]\n"):].split("\n\n")[0]
    toml = tmp_path / name
    toml.write_text("".join(line.removeprefix("# ") + "\n" for line in table.splitlines()))
    opts = zenoh_options(_parse(), str(toml))
    assert opts.tls_ca == "/etc/wardmap/tls/ca.crt" and opts.tls_cert.endswith(".crt")
    assert opts.tls_key == opts.tls_cert.removesuffix(".crt") + ".key"
