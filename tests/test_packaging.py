"""Packaging: every module imports from the editable install and from a built wheel,
under the ``wardmap`` namespace only (no bare top-level ``shared`` or ``server``)."""

from __future__ import annotations

import importlib
import importlib.util
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("cli", "edge", "server", "shared", "sim", "tools")
NEEDS_EXTRA = {"wardmap.tools.training.training": "torch"}
"""Modules of an optional extra (``train``): imported only where its package is installed."""


def _modules() -> list[str]:
    names = []
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            rel = f.relative_to(ROOT / pkg).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            if parts and parts[-1] == "__main__":
                continue
            name = ".".join(["wardmap", pkg, *parts])
            extra = NEEDS_EXTRA.get(name)
            if extra is None or importlib.util.find_spec(extra) is not None:
                names.append(name)
    return names


def test_every_module_imports_from_the_install() -> None:
    """Import each module by its wardmap.* name in this environment."""
    for name in _modules():
        importlib.import_module(name)


@pytest.mark.slow
def test_built_wheel_imports_every_module(tmp_path: Path) -> None:
    """Build a wheel, unpack it, and import every module from the unpacked copy."""
    out = tmp_path / "dist"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(out),
            str(ROOT),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    wheels = list(out.glob("wardmap-*.whl"))
    assert len(wheels) == 1
    with zipfile.ZipFile(wheels[0]) as zf:
        names = zf.namelist()
        zf.extractall(tmp_path / "site")
    top = {n.split("/")[0] for n in names}
    assert not top & set(PACKAGES), top  # only wardmap/ and its dist-info
    assert "wardmap/shared/data/knowledge_graph.toml" in names
    assert "wardmap/server/models/hospital_seg.onnx" in names  # the trained network ships
    # The web page and the API docs work offline: their files ship.
    for asset in ("index.html", "wardmap.js", "wardmap.css", "favicon.svg",
                  "vendor/swagger-ui/swagger-ui-bundle.js", "vendor/swagger-ui/swagger-ui.css",
                  "vendor/swagger-ui/LICENSE", "vendor/redoc/redoc.standalone.js", "vendor/redoc/LICENSE"):
        assert f"wardmap/server/api/static/{asset}" in names, asset
    script = (
        "import importlib, sys\n"
        f"mods = {_modules()!r}\n"
        "for m in mods:\n"
        "    mod = importlib.import_module(m)\n"
        "    assert mod.__file__.startswith(sys.argv[1]), (m, mod.__file__)\n"
        "from wardmap.shared.knowledge import KnowledgeGraph\n"
        "assert KnowledgeGraph.load().names\n"
    )
    env = dict(os.environ, PYTHONPATH=str(tmp_path / "site"))
    subprocess.run(
        [sys.executable, "-c", script, str(tmp_path / "site")], check=True, env=env, cwd=tmp_path, timeout=120
    )


TRAIN_MODULES = ("tools/training/training.py", "tools/training/logit_adjust.py", "tools/training/sitedata.py")
"""The only files that may import the ``train`` extra's packages (they say so when missing)."""
EXTRA_MODULES = {
    "train": TRAIN_MODULES, "export": ("tools/export.py",), "rerun": ("tools/export.py",),
    "postgres": ("server/store/postgres.py",), "realsense": ("edge/realsense.py",),
}
"""Per optional extra, the only files that may import its packages (inside the function that
needs them, saying so when missing)."""
NO_EXTRA_MODULES = {"pyorbbecsdk2": ("edge/orbbec.py",), "pyorbbecsdk": ("edge/orbbec.py",)}
"""Distributions installed by hand (no extra: their declared requirements would break the
install; docs/sources.md), and the only files that may import them (by distribution name, or by
module name where it is not installed)."""


def _requirement_names(reqs: list[str]) -> set[str]:
    import re

    return {re.split(r"[\s<>=!~;\[(]", r, maxsplit=1)[0].lower().replace("_", "-") for r in reqs}


def _closure(names: set[str]) -> set[str]:
    """``names`` and every distribution they require, transitively (installed ones only)."""
    from importlib import metadata

    seen: set[str] = set()
    todo = list(names)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        try:
            reqs = metadata.requires(name) or []
        except metadata.PackageNotFoundError:
            continue
        todo.extend(_requirement_names([r for r in reqs if "extra ==" not in r]))
    return seen


def test_every_third_party_import_is_a_declared_dependency() -> None:
    """A plain ``pip install .`` must run every command: each third-party module the code
    imports (at the top or inside a function) comes from a core dependency or one of theirs;
    only the training modules may use the ``train`` extra, only ``tools/export.py`` the
    ``export`` and ``rerun`` ones, only the PostgreSQL store the ``postgres`` one. (httpx, used
    by ``wardmap demo``, once sat in the ``dev`` extra only and the demo failed after a plain
    install.)"""
    import ast
    import tomllib
    from importlib import metadata

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    allowed = _closure(_requirement_names(project["dependencies"]))
    extras = {name: _requirement_names(project["optional-dependencies"][name]) for name in EXTRA_MODULES}
    dist_of = {
        m: [d.lower().replace("_", "-") for d in ds] for m, ds in metadata.packages_distributions().items()
    }
    missing = []
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(f.read_text(), str(f))):
                if isinstance(node, ast.Import):
                    tops = [a.name.split(".")[0] for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    tops = [node.module.split(".")[0]]
                else:
                    continue
                for top in tops:
                    if top in sys.stdlib_module_names or top in ("wardmap", "__future__"):
                        continue
                    dists = set(dist_of.get(top, [top]))
                    rel = f.relative_to(ROOT).as_posix()
                    if (dists & allowed or any(dists & extras[e] and rel in EXTRA_MODULES[e] for e in extras)
                            or any(d in dists and rel in files for d, files in NO_EXTRA_MODULES.items())):
                        continue
                    missing.append(f"{rel}:{node.lineno} imports {top} ({sorted(dists)})")
    assert not missing, "not a core dependency:\n" + "\n".join(missing)
