"""Static checks of the deployment files (no Docker engine here): every command they run parses
with the real ``wardmap`` CLI, every file they copy exists, images are pinned and run as non-root."""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

from wardmap.cli.main import build_parser

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILES = sorted((ROOT / "docker").glob("*.Dockerfile"))
UNITS = sorted((ROOT / "deploy" / "systemd").glob("*.service"))


def _parses(argv: list[str]) -> None:
    """The wardmap CLI accepts ``argv`` (argparse exits with code 2 otherwise)."""
    try:
        build_parser().parse_args(argv)
    except SystemExit as exc:  # pragma: no cover - the failure path
        pytest.fail(f"wardmap {' '.join(argv)}: rejected by the CLI (exit {exc.code})")


def _instructions(path: Path) -> list[tuple[str, str]]:
    text = re.sub(r"\\\n", " ", path.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            op, _, rest = line.partition(" ")
            out.append((op.upper(), rest.strip()))
    return out


def test_there_are_deployment_files() -> None:
    assert {p.name for p in DOCKERFILES} == {"edge.Dockerfile", "server.Dockerfile"}
    names = {p.name for p in UNITS}
    assert names == {"wardmap-edge.service", "wardmap-router.service", "wardmap-server.service"}


@pytest.mark.parametrize("path", DOCKERFILES, ids=lambda p: p.name)
def test_dockerfile(path: Path) -> None:
    ins = _instructions(path)
    ops = [op for op, _ in ins]
    base = dict(ins)["FROM"]
    assert re.match(r"^python:\d+\.\d+\.\d+-slim-\w+$", base), f"unpinned base image {base}"
    for op, rest in ins:
        if op == "COPY":
            *sources, _dest = rest.split()
            for src in sources:
                assert (ROOT / src).exists(), f"{path.name}: COPY {src}: no such file in the repository"
    user = [rest for op, rest in ins if op == "USER"]
    assert user and user[-1] not in ("root", "0"), "the image must not run as root"
    entry = json.loads(dict(ins)["ENTRYPOINT"])
    cmd = json.loads(dict(ins)["CMD"])
    assert entry == ["wardmap"]
    _parses(cmd)
    assert ops.index("USER") > ops.index("RUN")  # install as root, run as the user


def test_compose_file() -> None:
    yaml = pytest.importorskip("yaml")
    doc = yaml.safe_load((ROOT / "deploy" / "compose.yaml").read_text())
    services = doc["services"]
    built = {s["image"] for s in services.values() if "build" in s}
    for name, svc in services.items():
        if "build" in svc:
            context = (ROOT / "deploy" / svc["build"]["context"]).resolve()
            assert (context / svc["build"]["dockerfile"]).is_file(), name
        else:
            assert svc["image"] in built, f"{name}: image {svc['image']} is built by no service"
        _parses(svc["command"])
        for dep in svc.get("depends_on", []):
            assert dep in services, f"{name} depends on unknown service {dep}"
        for vol in svc.get("volumes", []):
            assert vol.split(":")[0] in doc["volumes"], f"{name}: undeclared volume {vol}"
        cmd = svc["command"]
        if "--connect" in cmd:
            host = cmd[cmd.index("--connect") + 1].split("/")[1].split(":")[0]
            assert host in services, f"{name} connects to {host}, not a service"


def _unit(path: Path) -> dict[str, dict[str, list[str]]]:
    """A systemd unit file as ``{section: {key: [values in order]}}`` (keys may repeat)."""
    out: dict[str, dict[str, list[str]]] = {}
    section = None
    for raw in re.sub(r"\\\n", " ", path.read_text()).splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            assert section not in out, f"{path.name}: section [{section}] twice"
            out[section] = {}
            continue
        assert section is not None and "=" in line, f"{path.name}: bad line {raw!r}"
        key, _, value = line.partition("=")
        out[section].setdefault(key.strip(), []).append(value.strip())
    return out


HARDENING = {  # what every unit sets (systemd.exec(5)); systemd-analyze scores the rest
    "NoNewPrivileges": "yes", "ProtectSystem": "strict", "PrivateTmp": "yes", "ProtectHome": "yes",
    "PrivateUsers": "yes", "ProtectKernelTunables": "yes", "ProtectKernelModules": "yes",
    "ProtectControlGroups": "yes", "RestrictSUIDSGID": "yes", "CapabilityBoundingSet": "",
    "SystemCallArchitectures": "native", "LockPersonality": "yes", "RestrictNamespaces": "yes",
}


@pytest.mark.parametrize("path", UNITS, ids=lambda p: p.name)
def test_systemd_unit(path: Path) -> None:
    """Each unit runs its real command line as the ``wardmap`` user that sysusers.d creates,
    hardened, with ``Type=notify`` (the commands send READY=1, ``shared/sdnotify.py``) and JSON
    logs for the journal's collectors."""
    unit = _unit(path)
    assert {"Unit", "Service", "Install"} <= set(unit)
    service = {key: values[-1] for key, values in unit["Service"].items()}
    (exec_start,) = unit["Service"]["ExecStart"]
    argv = shlex.split(exec_start)
    assert argv[0].endswith("/wardmap")
    _parses(argv[1:])
    assert argv[argv.index("--log-format") + 1] == "json"
    assert service["User"] == service["Group"] == "wardmap"
    assert (service["Type"], service["NotifyAccess"]) == ("notify", "main")
    for key, value in HARDENING.items():
        assert service.get(key) == value, f"{path.name}: {key}={service.get(key)!r}, want {value!r}"
    assert unit["Service"]["SystemCallFilter"][0] == "@system-service"
    if "--db" in argv or "--outbox" in argv:  # what it writes lies in its state folder
        target = argv[argv.index("--db") + 1] if "--db" in argv else argv[argv.index("--outbox") + 1]
        assert service["StateDirectory"] == "wardmap" and "/var/lib/wardmap/" in target


def test_sysusers_creates_the_units_user() -> None:
    """``deploy/sysusers.d/wardmap.conf`` creates the system user the units run as, with its
    home in their state folder."""
    lines = [ln.split() for ln in (ROOT / "deploy" / "sysusers.d" / "wardmap.conf").read_text().splitlines()
             if ln.strip() and not ln.startswith("#")]
    users = [shlex.split(" ".join(ln)) for ln in lines if ln[0] == "u"]
    assert [(u[1], u[2], u[-1]) for u in users] == [("wardmap", "-", "/var/lib/wardmap")]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed")
@pytest.mark.parametrize("path", UNITS, ids=lambda p: p.name)
def test_systemd_unit_scores_ok_or_better(path: Path) -> None:
    """``systemd-analyze security --offline`` rates each unit "OK" or better (exposure below 5.0
    of 10; the unhardened units scored 9.2 "UNSAFE")."""
    run = subprocess.run(["systemd-analyze", "security", "--offline=yes", "--threshold=49", str(path)],
                         capture_output=True, text=True, timeout=60, check=False)
    m = re.search(r"Overall exposure level for \S+: (\d+\.\d) (\w+)", run.stdout)
    assert m is not None, run.stdout[-2000:] + run.stderr[-2000:]
    assert float(m.group(1)) < 5.0 and m.group(2) in ("PERFECT", "SAFE", "OK"), m.group(0)
    assert run.returncode == 0, m.group(0)


def test_no_deployment_file_serves_the_api_without_tokens() -> None:
    """``--insecure-loopback`` (the demo's and the tests' mode) appears in no deployment file:
    the deployed REST API always asks for a token."""
    deploy = ROOT / "deploy"
    files = [*DOCKERFILES, *UNITS, *sorted(deploy.glob("*.yaml")), *sorted(deploy.glob("*.toml"))]
    for path in files:
        assert "insecure-loopback" not in path.read_text(), path.name
