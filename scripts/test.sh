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
# Orbbec SDK v2's bindings for the orbbec source's tests (x86_64 Linux wheel), without the wheel's
# declared requirements (numpy<2, open3d, pygame: its examples' needs; docs/sources.md).
if [ "$(uname -sm)" = "Linux x86_64" ]; then
    "$VENV/bin/python" -m pip install -q --no-deps "pyorbbecsdk2>=2.1"
fi
# The web page's browser tests drive Debian's chromium through Playwright (no browser download).
if ! command -v chromium >/dev/null 2>&1; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -q && apt-get install -y -q chromium </dev/null
    else
        echo "scripts/test.sh: no chromium and no root apt-get to install it; browser tests will skip" >&2
    fi
fi
# The store tests start their own PostgreSQL 15 cluster (tests/pgcluster.py) and test the object
# index with and without PostGIS; install the server and PostGIS where they are missing.
if [ ! -x /usr/lib/postgresql/15/bin/initdb ] || [ ! -f /usr/share/postgresql/15/extension/postgis.control ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -q && apt-get install -y -q postgresql-15 postgresql-15-postgis-3 </dev/null
    else
        echo "scripts/test.sh: no PostgreSQL 15 + PostGIS and no root apt-get to install them; those tests will skip" >&2
    fi
fi
# The suite writes up to about 3 GB at a time (map databases, outboxes, bags, PostgreSQL clusters);
# say so up front instead of failing later with "No space left on device".
TMP_FREE_MB=$(df -Pm "${TMPDIR:-/tmp}" | awk 'NR == 2 {print $4}')
if [ "${TMP_FREE_MB:-0}" -lt 4096 ]; then
    echo "scripts/test.sh: only ${TMP_FREE_MB} MB free under ${TMPDIR:-/tmp}; the tests need about 3 GB" >&2
fi
"$VENV/bin/ruff" check .
# mypy sees the source folders under their installed names (wardmap.shared, ...).
TYPECHECK=build/typecheck
rm -rf "$TYPECHECK" && mkdir -p "$TYPECHECK/wardmap"
for d in cli edge server shared sim tools; do ln -s "$PWD/$d" "$TYPECHECK/wardmap/$d"; done
MYPYPATH="$TYPECHECK" "$VENV/bin/mypy" -p wardmap
# The layering of docs/ARCHITECTURE.md: import-linter contracts in pyproject.toml.
"$VENV/bin/lint-imports" --no-cache --no-logo
"$VENV/bin/python" -m pytest -q "$@"
