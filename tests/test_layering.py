"""The layering of docs/ARCHITECTURE.md: the import-linter contracts in ``pyproject.toml`` hold on
the real tree and break on a planted violation of each.

A planted violation goes into a temporary tree: ``wardmap/<package>`` links to each real
package folder, except the one under test, which is a copy with one extra module. import-linter
runs in a child Python started with ``-S`` (no ``.pth`` files, so the editable install's finder
cannot point ``wardmap.*`` back at the real folders) whose path is the temporary tree, then the
environment's site-packages (import-linter and its dependencies).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("cli", "edge", "server", "shared", "sim", "tools")
CONFIG = ROOT / "pyproject.toml"
LINT = "from importlinter.cli import lint_imports_command; lint_imports_command()"


def _tree(tmp_path: Path, planted: str | None = None, source: str = "") -> Path:
    """A ``wardmap`` namespace folder under ``tmp_path`` with every package linked in; with
    ``planted``, that package is a copy holding one more module, ``_planted.py`` = ``source``."""
    pkg_root = tmp_path / "tree" / "wardmap"
    pkg_root.mkdir(parents=True)
    for name in PACKAGES:
        if name == planted:
            shutil.copytree(ROOT / name, pkg_root / name,
                            ignore=shutil.ignore_patterns("__pycache__", "*.onnx"))
            (pkg_root / name / "_planted.py").write_text(source)
        else:
            (pkg_root / name).symlink_to(ROOT / name, target_is_directory=True)
    return pkg_root.parent


def _lint(tree: Path) -> tuple[int, str]:
    """Run ``lint-imports`` with the project's contracts on the packages under ``tree`` only:
    ``(exit code, output)``."""
    paths = sysconfig.get_paths()
    search = [str(tree), *dict.fromkeys([paths["purelib"], paths["platlib"]])]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PYTHONPATH"] = os.pathsep.join(search)
    done = subprocess.run(
        [sys.executable, "-S", "-c", LINT, "--no-cache", "--no-logo", str(CONFIG)],
        capture_output=True, text=True, env=env, cwd=tree, timeout=120,
    )
    return done.returncode, done.stdout + done.stderr


def _broken(output: str) -> set[str]:
    return set(re.findall(r"^(.+) BROKEN$", output, re.MULTILINE))


def _source_files() -> int:
    return sum(1 for name in PACKAGES for _ in (ROOT / name).rglob("*.py"))


def test_contracts_hold_in_the_installed_tree() -> None:
    """``lint-imports`` as scripts/test.sh runs it (the editable install) keeps every contract."""
    lint = Path(sys.executable).with_name("lint-imports")
    done = subprocess.run([str(lint), "--no-cache", "--no-logo"], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "0 broken" in done.stdout


def test_contracts_hold_on_the_linked_tree(tmp_path: Path) -> None:
    """The harness itself: on links to the real packages every contract is kept, and every
    source file was analysed (so a planted module below is seen, not skipped)."""
    rc, out = _lint(_tree(tmp_path))
    assert rc == 0, out
    analysed = re.search(r"Analyzed (\d+) files", out)
    assert analysed is not None, out
    assert int(analysed.group(1)) == _source_files()


PLANTED = [
    pytest.param("server", "import wardmap.sim.world\n", "server and edge never import sim or tools",
                 id="server-imports-sim"),
    # imports inside functions count as well (the code base imports heavy packages lazily)
    pytest.param("edge", "def f() -> None:\n    from wardmap.tools import demo\n",
                 "server and edge never import sim or tools", id="edge-imports-tools-lazily"),
    pytest.param("edge", "from wardmap.server import store\n", "edge and server never import each other",
                 id="edge-imports-server"),
    pytest.param("server", "import wardmap.edge.outbox\n", "edge and server never import each other",
                 id="server-imports-edge"),
    pytest.param("sim", "from wardmap.server.perception import types\n", "sim imports only shared",
                 id="sim-imports-server"),
    pytest.param("shared", "import wardmap.sim.raster\n", "shared imports nothing of ours",
                 id="shared-imports-sim"),
    pytest.param("tools", "from wardmap.cli.server_cmd import parse_http\n", "cli is imported by nothing",
                 id="tools-imports-cli"),
]


@pytest.mark.parametrize(("package", "source", "contract"), PLANTED)
def test_a_planted_violation_breaks_its_contract(tmp_path: Path, package: str, source: str,
                                                 contract: str) -> None:
    """One forbidden import planted in a copy of ``package`` makes lint-imports fail and name
    the contract it breaks."""
    rc, out = _lint(_tree(tmp_path, package, source))
    assert rc != 0, out
    assert contract in _broken(out), out
    assert f"wardmap.{package}._planted" in out
