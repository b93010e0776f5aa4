#!/usr/bin/env bash
# Set up a virtual environment from scratch (if needed) and run lint, types and tests.
# Usage: bash scripts/test.sh [pytest args...]
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${VENV:-.venv}
if [ ! -x "$VENV/bin/python" ]; then
    "$PY" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip "setuptools>=68" wheel
"$VENV/bin/python" -m pip install -q -e '.[dev]'
"$VENV/bin/ruff" check .
# mypy sees the source folders under their installed names (wardmap.shared, ...).
TYPECHECK=build/typecheck
rm -rf "$TYPECHECK" && mkdir -p "$TYPECHECK/wardmap"
for d in cli edge server shared sim tools; do ln -s "$PWD/$d" "$TYPECHECK/wardmap/$d"; done
MYPYPATH="$TYPECHECK" "$VENV/bin/mypy" -p wardmap
# The layering of docs/ARCHITECTURE.md: import-linter contracts in pyproject.toml.
"$VENV/bin/lint-imports" --no-cache --no-logo
"$VENV/bin/python" -m pytest -q "$@"
