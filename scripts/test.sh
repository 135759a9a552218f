#!/usr/bin/env bash
# The tests as CI runs them: lint, format check, then the whole suite on every core
# (pytest-xdist), skips listed, the 20 slowest tests named.
# Usage: scripts/test.sh [pytest args...]   (after scripts/setup.sh --dev)
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/python -m pytest -q -rs -n auto --durations=20 "$@"
