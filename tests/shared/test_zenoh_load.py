"""Tests of wardmap.shared.zenoh_load: a site's zenoh config file under wardmap's values, and
the TLS checks made before zenoh connects (real ``zenoh.Config`` objects, no session)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("zenoh")

from wardmap.shared.errors import ConfigError
from wardmap.shared.zenoh_config import ZenohOptions, client_config, router_config
from wardmap.shared.zenoh_load import connect_hint, load_zenoh_config


@pytest.fixture
def pem(tmp_path: Path) -> dict[str, str]:
    """Paths of three existing files standing in for PEM files (only their existence is checked)."""
    out = {}
    for name in ("ca", "cert", "key"):
        (tmp_path / f"{name}.pem").write_text("-----BEGIN-----\n")
        out[name] = str(tmp_path / f"{name}.pem")
    return out


def test_tls_files_from_the_site_file_or_the_options(tmp_path: Path, pem: dict[str, str]) -> None:
    """A client on tls/ takes its CA from the site file when no option sets it, and from the
    option (over the file) when both do; endpoints always come from wardmap."""
    site = tmp_path / "zenoh.json5"
    site.write_text(json.dumps({"connect": {"endpoints": ["tcp/10.0.0.1:1"]},
                                "transport": {"link": {"tls": {"root_ca_certificate": pem["key"]}}}}))
    endpoint = ["tls/127.0.0.1:7447"]
    conf = load_zenoh_config(client_config(endpoint), ZenohOptions(config=str(site)))
    assert json.loads(conf.get_json("transport/link/tls/root_ca_certificate")) == pem["key"]
    assert json.loads(conf.get_json("connect/endpoints")) == endpoint
    opts = ZenohOptions(config=str(site), tls_ca=pem["ca"], tls_cert=pem["cert"], tls_key=pem["key"])
    conf = load_zenoh_config(client_config(endpoint, options=opts), opts)
    assert json.loads(conf.get_json("transport/link/tls/root_ca_certificate")) == pem["ca"]
    assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is True


@pytest.mark.parametrize(
    ("side", "endpoint", "options", "match"),
    [
        ("client", "tls/127.0.0.1:7447", {}, "needs --tls-ca"),
        ("client", "quic/127.0.0.1:7447", {}, "needs --tls-ca"),
        ("router", "tls/0.0.0.0:7447", {"tls_ca": "ca"}, "needs --tls-cert"),
        ("client", "tcp/127.0.0.1:7447", {"tls_ca": "/no/such/ca.pem"}, "TLS file not found: /no/such/ca"),
        ("client", "tcp/127.0.0.1:7447", {"config": "/no/such.json5"}, "zenoh config file not found"),
    ],
)
def test_missing_tls_files_are_one_line_config_errors(
    pem: dict[str, str], side: str, endpoint: str, options: dict[str, str], match: str
) -> None:
    """A tls/ or quic/ endpoint without its CA (client) or certificate (router), a TLS file or
    config file that does not exist: ConfigError naming the flag or file, before connecting."""
    opts = ZenohOptions(**{k: pem.get(v, v) for k, v in options.items()})
    make = router_config if side == "router" else client_config
    ours = make([endpoint], options=opts)
    with pytest.raises(ConfigError, match=match):
        load_zenoh_config(ours, opts)


def test_connect_hint_only_for_tls() -> None:
    """The hint about certificates is added to failed tls/ and quic/ connects only."""
    assert connect_hint(["tcp/127.0.0.1:7447"]) == ""
    assert "--tls-ca" in connect_hint(["tls/127.0.0.1:7447"])
    assert "--tls-ca" in connect_hint(["quic/127.0.0.1:7447"])
