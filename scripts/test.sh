#!/usr/bin/env bash
# The tests as CI runs them: lint, format check, then the whole suite on every core
# (pytest-xdist, a worker more than cores, work stealing), skips listed, the 20 slowest named.
# Usage: scripts/test.sh [pytest args...]   (after scripts/setup.sh --dev)
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff check .
.venv/bin/ruff format --check .
# The suite starts dozens of Python processes (workers, CLI children, peers): let them share
# compiled bytecode. Where PYTHONDONTWRITEBYTECODE is set, each compiled torch & co. (and
# pytest each test module's rewritten asserts) from source again: 3.9 s instead of 2.1 s for
# `import torch` alone. The files go to __pycache__ folders that git ignores.
unset PYTHONDONTWRITEBYTECODE
# One worker more than cores: the live, browser and peer tests spend about a fifth of the
# suite's worker time waiting on real time, and the extra worker fills those gaps (each
# worker's runtimes get one thread, tests/conftest.py).
workers=$(( $(.venv/bin/python -c "import os; print(len(os.sched_getaffinity(0)))") + 1 ))
# --dist worksteal: a worker that runs out takes half of the busiest one's queue. With the
# default (load), the last two tests queued on one worker were the two slowest training tests
# (21 s) while the others had finished: the workers ended 17 s apart, 5 s with worksteal.
.venv/bin/python -m pytest -q -rs -n "$workers" --dist worksteal --durations=20 "$@"
