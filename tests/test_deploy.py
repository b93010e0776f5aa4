"""Static checks of the deployment files (no Docker engine here): every command they run parses
with the real ``wardmap`` CLI, every file they copy exists, images are pinned and run as non-root."""

from __future__ import annotations

import configparser
import json
import re
import shlex
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


@pytest.mark.parametrize("path", UNITS, ids=lambda p: p.name)
def test_systemd_unit(path: Path) -> None:
    unit = configparser.ConfigParser(strict=True, interpolation=None)
    unit.read_string(path.read_text())
    assert {"Unit", "Service", "Install"} <= set(unit.sections())
    argv = shlex.split(unit["Service"]["ExecStart"])
    assert argv[0].endswith("/wardmap")
    _parses(argv[1:])
    assert unit["Service"]["User"] == "wardmap"


def test_no_deployment_file_serves_the_api_without_tokens() -> None:
    """``--insecure-loopback`` (the demo's and the tests' mode) appears in no deployment file:
    the deployed REST API always asks for a token."""
    deploy = ROOT / "deploy"
    files = [*DOCKERFILES, *UNITS, *sorted(deploy.glob("*.yaml")), *sorted(deploy.glob("*.toml"))]
    for path in files:
        assert "insecure-loopback" not in path.read_text(), path.name
