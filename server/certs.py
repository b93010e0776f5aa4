"""A site's certificate authority for Zenoh mutual TLS, and the router ACL of its fleet.

One folder (``wardmap certs --out DIR``) holds the site:

- ``ca.crt`` / ``ca.key``: the site CA (:func:`init_ca`), a self-signed ECDSA P-256 CA;
- ``NAME.crt`` / ``NAME.key``: one per router, server and robot (:func:`issue`), signed by
  the CA, common name ``NAME`` (the robot id for a robot: the ACL's subject), the role in the
  organizational unit (``wardmap robot|server|router``), both client and server usage; a
  router's certificate names the hosts robots dial (``--host``), which clients verify;
- ``acl.json5``: a Zenoh config holding the router's ``access_control``
  (:func:`~wardmap.shared.zenoh_config.access_control`), rewritten from the robot and server
  certificates in the folder after each issue (:func:`write_acl`): the folder is the fleet
  list. Deleting ``NAME.crt`` and rewriting the ACL removes a robot's rights (the router
  reads the ACL at start).

Private keys are PKCS#8 PEM without a passphrase, created with mode 0600; no file is ever
overwritten (except the derived ``acl.json5``). Uses the ``cryptography`` library.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from wardmap.shared.errors import ConfigError, WardmapError
from wardmap.shared.zenoh_config import access_control

__all__ = [
    "ACL_FILE",
    "CA_CERT",
    "CA_KEY",
    "CertError",
    "Issued",
    "Role",
    "fleet",
    "init_ca",
    "issue",
    "write_acl",
]

Role = Literal["robot", "server", "router"]
CA_CERT = "ca.crt"
CA_KEY = "ca.key"
ACL_FILE = "acl.json5"
_OU_PREFIX = "wardmap "
_NAME_RE = re.compile(r"[A-Za-z0-9_.-]{1,64}")
_HOST_RE = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9])?")
CA_DAYS = 3650
"""Validity of the site CA (days)."""


class CertError(WardmapError):
    """A certificate cannot be made or read (a file exists, the CA is missing, a bad name)."""


@dataclass(frozen=True)
class Issued:
    """Files written by :func:`issue` (paths) and the fleet the ACL now lists."""

    cert: Path
    key: Path
    acl: Path | None
    robots: tuple[str, ...]
    servers: tuple[str, ...]


def _now() -> datetime.datetime:
    return datetime.datetime.now(datetime.UTC)


def _refuse_existing(*paths: Path) -> None:
    for path in paths:
        if path.exists():
            raise CertError(f"{path} exists; refusing to overwrite it (move it away first)")


def _write_new(path: Path, data: bytes, mode: int) -> None:
    """Create ``path`` with ``mode`` (never replacing a file) and write ``data``."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    except FileExistsError:
        raise CertError(f"{path} exists; refusing to overwrite it (move it away first)") from None
    except OSError as exc:
        raise CertError(f"cannot create {path}: {exc.strerror}") from exc
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)
    os.chmod(path, mode)  # the umask may have removed bits of a public file's 0644


def _key_and_pem() -> tuple[ec.EllipticCurvePrivateKey, bytes]:
    key = ec.generate_private_key(ec.SECP256R1())
    pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    return key, pem


def _check_name(name: str) -> str:
    if not isinstance(name, str) or _NAME_RE.fullmatch(name) is None or name in ("ca", "acl"):
        raise CertError(f"bad name {name!r}: expected 1-64 characters from [A-Za-z0-9_.-], not 'ca' or 'acl'")
    return name


def init_ca(out: str | Path, *, common_name: str = "wardmap site CA") -> Path:
    """Create the site CA in folder ``out`` (created if missing): ``ca.crt`` and ``ca.key``.

    Returns the certificate's path. Raises CertError when either file exists.
    """
    out = Path(out)
    cert_path, key_path = out / CA_CERT, out / CA_KEY
    _refuse_existing(cert_path, key_path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CertError(f"cannot create {out}: {exc.strerror}") from exc
    key, key_pem = _key_and_pem()
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    now = _now()
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=CA_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                          key_encipherment=False, data_encipherment=False, key_agreement=False,
                          encipher_only=False, decipher_only=False),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write_new(key_path, key_pem, 0o600)
    _write_new(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return cert_path


def _load_ca(out: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    cert_path, key_path = out / CA_CERT, out / CA_KEY
    if not cert_path.is_file() or not key_path.is_file():
        raise CertError(f"no site CA in {out}: run `wardmap certs init --out {out}` first")
    try:
        ca_cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        ca_key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (ValueError, TypeError) as exc:
        raise CertError(f"cannot read the site CA in {out}: {exc}") from exc
    if not isinstance(ca_key, ec.EllipticCurvePrivateKey):
        raise CertError(f"{key_path} is not an EC key made by `wardmap certs init`")
    return ca_cert, ca_key


def _san(name: str, role: Role, hosts: Sequence[str]) -> list[x509.GeneralName]:
    entries: list[x509.GeneralName] = []
    for host in hosts:
        try:
            entries.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            if _HOST_RE.fullmatch(host) is None:
                raise CertError(f"bad --host {host!r}: expected a DNS name or an IP address") from None
            entries.append(x509.DNSName(host))
    if role == "router" and not entries:
        raise CertError("a router certificate needs --host HOST (repeatable): the names or addresses "
                        "robots and servers connect to, e.g. --host 192.0.2.10 --host router.ward.local")
    if not entries:
        entries.append(x509.DNSName(name))
    return entries


def issue(
    out: str | Path, name: str, role: Role, *, hosts: Sequence[str] = (), days: int = 825
) -> Issued:
    """Issue ``NAME.crt`` / ``NAME.key`` in ``out``, signed by the CA there, then rewrite the ACL.

    Args:
        out: the site folder (``ca.crt``/``ca.key`` from :func:`init_ca`).
        name: the certificate's common name: the robot id for a robot (what the ACL matches).
        role: ``robot``, ``server`` or ``router``.
        hosts: DNS names or IP addresses the certificate is valid for (its subject alternative
            names); required for a router (clients verify the host they dial).
        days: validity in days (1..3650).

    Raises:
        CertError: a bad name, role, host or validity; a file exists; no CA in ``out``.
    """
    out = Path(out)
    _check_name(name)
    if role not in get_args(Role):
        raise CertError(f"bad role {role!r}: expected one of {', '.join(get_args(Role))}")
    if isinstance(days, bool) or not isinstance(days, int) or not 1 <= days <= CA_DAYS:
        raise CertError(f"bad --days {days!r}: expected 1..{CA_DAYS}")
    if role == "robot":
        try:
            access_control([name], [])  # the ACL takes it as a robot id
        except ConfigError as exc:
            raise CertError(str(exc)) from exc
    cert_path, key_path = out / f"{name}.crt", out / f"{name}.key"
    _refuse_existing(cert_path, key_path)
    ca_cert, ca_key = _load_ca(out)
    san = _san(name, role, hosts)
    key, key_pem = _key_and_pem()
    now = _now()
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([
            x509.NameAttribute(NameOID.COMMON_NAME, name),
            x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, _OU_PREFIX + role),
        ]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(min(now + datetime.timedelta(days=days), ca_cert.not_valid_after_utc))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(x509.SubjectAlternativeName(san), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )
    _write_new(key_path, key_pem, 0o600)
    _write_new(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    robots, servers = fleet(out)
    acl = write_acl(out) if robots or servers else None
    return Issued(cert_path, key_path, acl, robots, servers)


def fleet(out: str | Path) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``(robots, servers)``: common names of the robot and server certificates in ``out``
    that the site CA signed (sorted).

    Raises:
        CertError: no CA in ``out``, or a ``*.crt`` that cannot be read.
    """
    robots, servers, _ = _fleet(out)
    return robots, servers


def _fleet(out: str | Path) -> tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]:
    """``(robots, servers, routers)`` of :func:`fleet`, routers' common names too."""
    out = Path(out)
    ca_cert, _ = _load_ca(out)
    robots: list[str] = []
    servers: list[str] = []
    routers: list[str] = []
    for path in sorted(out.glob("*.crt")):
        if path.name == CA_CERT:
            continue
        try:
            cert = x509.load_pem_x509_certificate(path.read_bytes())
            cert.verify_directly_issued_by(ca_cert)
        except (ValueError, TypeError) as exc:
            raise CertError(f"{path} is not a certificate of the site CA in {out}: {exc}") from exc
        cn = [a.value for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)]
        ou = [a.value for a in cert.subject.get_attributes_for_oid(NameOID.ORGANIZATIONAL_UNIT_NAME)]
        role = str(ou[0]).removeprefix(_OU_PREFIX) if ou else ""
        if role == "robot":
            robots.append(str(cn[0]))
        elif role == "server":
            servers.append(str(cn[0]))
        elif role == "router":
            routers.append(str(cn[0]))
    return tuple(robots), tuple(servers), tuple(routers)


def write_acl(out: str | Path) -> Path:
    """Rewrite ``out/acl.json5`` from the fleet in ``out`` (routers' certificates with the servers'
    rights: a mesh of routers passes everything); returns its path.

    Raises:
        CertError: no CA, an unreadable certificate, or an empty fleet.
    """
    out = Path(out)
    robots, servers, routers = _fleet(out)
    try:
        # A router joined to another one (`wardmap router --connect`) forwards every robot's and
        # server's messages, so it has the servers' rights on the other router.
        acl = access_control(robots, tuple(sorted(servers + routers)))
    except ConfigError as exc:
        raise CertError(f"{out}: {exc}") from exc
    path = out / ACL_FILE
    text = (
        "// Written by `wardmap certs` from the robot and server certificates in this folder;\n"
        "// regenerate with `wardmap certs acl --out DIR`, do not edit (docs/security.md).\n"
        "// The router loads it with --zenoh-config; it needs a tls/ listen endpoint with mutual TLS.\n"
        + json.dumps({"access_control": acl}, indent=2)
        + "\n"
    )
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)
    return path
