"""Tests of wardmap.server.certs (``wardmap certs``): a site CA, issued certificates, the ACL file.

Real files in a temporary folder, read back with ``cryptography`` and zenoh's own config parser.
"""

from __future__ import annotations

import stat
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
from procs import one_line_error, wardmap

from wardmap.server.certs import ACL_FILE, CertError, fleet, init_ca, issue, write_acl


@pytest.fixture
def site(tmp_path: Path) -> Path:
    """A site folder with its CA."""
    init_ca(tmp_path / "site")
    return tmp_path / "site"


def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_ca_and_issued_certificates(site: Path) -> None:
    """The CA is a CA; a robot's certificate has CN = robot id, is signed by the CA, serves both
    ends of TLS; a router's names its hosts; keys are 0600, certificates 0644."""
    ca = _cert(site / "ca.crt")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is True
    robot = issue(site, "robot_0", "robot")
    router = issue(site, "router", "router", hosts=["127.0.0.1", "router.ward.local"])
    for issued in (robot, router):
        cert = _cert(issued.cert)
        cert.verify_directly_issued_by(ca)
        usage = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH} <= set(usage)
        assert stat.S_IMODE(issued.key.stat().st_mode) == 0o600
        assert stat.S_IMODE(issued.cert.stat().st_mode) == 0o644
    assert stat.S_IMODE((site / "ca.key").stat().st_mode) == 0o600
    assert _cert(robot.cert).subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "robot_0"
    names = _cert(router.cert).extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert [str(ip) for ip in names.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    assert names.get_values_for_type(x509.DNSName) == ["router.ward.local"]


def test_acl_follows_the_certificates_in_the_folder(site: Path) -> None:
    """Each robot or server issue rewrites acl.json5 (routers stay out of it); zenoh parses the
    file; a removed certificate leaves the ACL at the next rewrite."""
    zenoh = pytest.importorskip("zenoh")
    issue(site, "router", "router", hosts=["127.0.0.1"])
    assert not (site / ACL_FILE).exists()  # no robot or server yet: nothing to allow
    issue(site, "server", "server")
    issue(site, "robot_0", "robot")
    last = issue(site, "robot_1", "robot")
    assert (last.robots, last.servers) == (("robot_0", "robot_1"), ("server",))
    conf = zenoh.Config.from_file(str(site / ACL_FILE))
    assert '"cert_common_names":["robot_1"]' in conf.get_json("access_control/subjects").replace(" ", "")
    (site / "robot_1.crt").unlink()
    write_acl(site)
    assert fleet(site) == (("robot_0",), ("server",))
    assert "robot_1" not in (site / ACL_FILE).read_text()


def test_nothing_is_overwritten_and_bad_input_is_refused(site: Path, tmp_path: Path) -> None:
    """An existing CA, certificate or key is never replaced; bad names, roles, hosts, a router
    without hosts and a folder without CA are CertErrors naming the problem."""
    issue(site, "robot_0", "robot")
    before = (site / "robot_0.key").read_bytes()
    with pytest.raises(CertError, match="exists"):
        init_ca(site)
    with pytest.raises(CertError, match="exists"):
        issue(site, "robot_0", "robot")
    assert (site / "robot_0.key").read_bytes() == before
    (site / "robot_1.key").write_text("someone's key")
    with pytest.raises(CertError, match=r"robot_1\.key exists"):
        issue(site, "robot_1", "robot")
    assert not (site / "robot_1.crt").exists()
    for kwargs, match in [
        ({"name": "a/b", "role": "robot"}, "bad name"),
        ({"name": "ca", "role": "server"}, "bad name"),
        ({"name": "x", "role": "admin"}, "bad role"),
        ({"name": "x", "role": "router"}, "needs --host"),
        ({"name": "x", "role": "router", "hosts": ["bad host!"]}, "bad --host"),
        ({"name": "x", "role": "robot", "days": 0}, "bad --days"),
    ]:
        with pytest.raises(CertError, match=match):
            issue(site, **kwargs)  # type: ignore[arg-type]
    with pytest.raises(CertError, match="wardmap certs init"):
        issue(tmp_path / "nowhere", "robot_0", "robot")


def test_cli_one_line_errors(site: Path) -> None:
    """``wardmap certs`` prints what it wrote; refusals are one line and exit 1."""
    done = wardmap("certs", "issue", "server", "--role", "server", "--out", str(site), timeout_s=60)
    assert done.returncode == 0, done.stderr
    assert f"wrote {site / ACL_FILE}: 0 robots, 1 servers" in done.stdout
    one_line_error(wardmap("certs", "init", "--out", str(site), timeout_s=60), "exists", "certs")
    one_line_error(wardmap("certs", "issue", "r", "--role", "router", "--out", str(site), timeout_s=60),
                   "needs --host", "certs")
