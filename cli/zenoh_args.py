"""The Zenoh options ``wardmap router``, ``server`` and ``edge`` share (docs/security.md).

``--zenoh-config FILE`` names a Zenoh JSON5 config laid under wardmap's values;
``--tls-ca``, ``--tls-cert`` and ``--tls-key`` name the PEM files of the common case (made by
``wardmap certs``). Each flag overrides the same key of the ``[zenoh]`` table of the
command's TOML ``--config`` (server and edge).
"""

from __future__ import annotations

import argparse
import dataclasses

from wardmap.shared.zenoh_config import ZenohOptions

_FLAGS = {
    "config": ("--zenoh-config", "zenoh JSON5 config file (e.g. the ACL of `wardmap certs`); "
               "wardmap's values override it"),
    "tls_ca": ("--tls-ca", "PEM file of the site CA: authenticates the router (and, on the "
               "router, the clients: mutual TLS)"),
    "tls_cert": ("--tls-cert", "PEM certificate of this process (from `wardmap certs issue`)"),
    "tls_key": ("--tls-key", "PEM private key of --tls-cert"),
}


def add_zenoh_args(p: argparse.ArgumentParser) -> None:
    """Add ``--zenoh-config``, ``--tls-ca``, ``--tls-cert`` and ``--tls-key`` to ``p``."""
    group = p.add_argument_group("zenoh security (docs/security.md)")
    for field, (flag, text) in _FLAGS.items():
        group.add_argument(flag, dest=f"zenoh_{field}", metavar="FILE", help=text)


def zenoh_options(args: argparse.Namespace, toml_path: str | None = None) -> ZenohOptions:
    """The ``[zenoh]`` table of ``toml_path`` (defaults when None) with the flags on top.

    Raises:
        ConfigError: a bad ``[zenoh]`` table, or a certificate without its key.
    """
    from wardmap.shared.config import load_config
    from wardmap.shared.errors import ConfigError

    base = load_config(ZenohOptions, toml_path, section="zenoh")
    flags = {f: getattr(args, f"zenoh_{f}") for f in _FLAGS if getattr(args, f"zenoh_{f}") is not None}
    try:
        return dataclasses.replace(base, **flags)
    except ValueError as exc:
        raise ConfigError(f"{exc} (--tls-cert, --tls-key)") from exc
