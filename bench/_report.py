"""Shared helpers of the benchmark scripts: machine description and BENCHMARKS.md sections."""

from __future__ import annotations

import argparse
import os
import platform
import re
import subprocess
import tomllib
from pathlib import Path
from typing import Any


def machine() -> str:
    """One line describing this machine (CPU model, cores, memory, Python)."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        kb = int(Path("/proc/meminfo").read_text().split()[1])
        mem = f", {kb / 2**20:.0f} GiB"
    except (OSError, ValueError, IndexError):
        pass
    return f"{cpu}, {os.cpu_count()} cores{mem}, Python {platform.python_version()}"


def git_rev() -> str:
    """Short hash of HEAD, marked when tracked files other than BENCHMARKS.md are modified (the
    figures then come from code that no commit holds)."""
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", ".", ":!BENCHMARKS.md"],
            capture_output=True, text=True, check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return f"{rev} with uncommitted changes" if dirty else rev


def publish(body: str, path: Path | None, name: str) -> None:
    """Print a bench's markdown ``body``; with ``path`` (``--write``), also put it in section ``name``."""
    print(body)
    if path is not None:
        write_section(path, name, body)


def write_section(path: Path, name: str, body: str) -> None:
    """Replace (or append) the section between ``<!-- name:start -->`` and ``<!-- name:end -->``."""
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    block = f"{start}\n{body.rstrip()}\n{end}"
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    pattern = re.compile(re.escape(start) + r".*?" + re.escape(end), re.S)
    text = (
        pattern.sub(lambda _m: block, text) if pattern.search(text) else text.rstrip() + "\n\n" + block + "\n"
    )
    path.write_text(text)


EVAL_SEEDS = (2001, 2002, 2003, 2004, 2005)
"""Evaluation worlds: benchmarks report on these by default; no setting is tuned on them."""
TUNE_SEEDS = (1001, 1002)
"""Tuning worlds: thresholds and rules are chosen on these. Training worlds are < 1000
(``wardmap.tools.training.segdata.EVAL_SEED_MIN``); the training validation split uses 1000."""


def add_seed_arguments(ap: argparse.ArgumentParser, data: Path) -> None:
    """``--data`` (cached simulated data sets) and ``--seeds`` (default :data:`EVAL_SEEDS`)."""
    ap.add_argument("--data", type=Path, default=data)
    ap.add_argument("--seeds", type=int, nargs="+", default=list(EVAL_SEEDS),
                    help=f"world seeds (default {' '.join(map(str, EVAL_SEEDS))}, the evaluation worlds; "
                    f"{' '.join(map(str, TUNE_SEEDS))} are tuning worlds, < 1000 the segmentation "
                    "network's training worlds)")


def tracker_config(items: list[str]) -> Any:
    """The ``TrackerConfig`` with ``--set`` items applied: each a TOML ``KEY=VALUE`` line of the
    ``[tracker]`` table (dotted keys for its sub-tables), validated as a config file is."""
    from wardmap.edge.tracker import TrackerConfig
    from wardmap.shared.config import from_mapping
    from wardmap.shared.errors import ConfigError

    try:
        return from_mapping(TrackerConfig, tomllib.loads("\n".join(items)), "tracker")
    except (tomllib.TOMLDecodeError, ConfigError) as exc:
        raise SystemExit(f"--set {' '.join(items)!r}: {exc}") from None
