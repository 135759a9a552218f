#!/usr/bin/env bash
# Set up beadsight in ./.venv. Usage: scripts/setup.sh [--dev]
#   (no flag)  the package with its hardware/export/ROS extras
#   --dev      also the test tools, and Debian's chromium for the browser tests
# torch is installed first and pinned: a bare "torch" requirement resolved from
# scratch pulls a multi-GB CUDA build, while torch==2.13.0 takes the local CPU build
# (on a CUDA machine the same pin installs the CUDA build).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
TORCH_SPEC=${BEADSIGHT_TORCH:-torch==2.13.0}
extras=all
[ "${1:-}" = "--dev" ] && extras=dev
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip 2>&1 | grep -v '^WARNING: Location' || true
.venv/bin/python -c "import torch" 2>/dev/null || .venv/bin/python -m pip install -q "$TORCH_SPEC" 2>&1 | grep -v '^WARNING: Location' || true
.venv/bin/python -m pip install -q -e ".[$extras]" 2>&1 | grep -v '^WARNING: Location' || true
.venv/bin/python -c "import beadsight, torch; print(f'beadsight {beadsight.__version__} ready (torch {torch.__version__}) in .venv')"
if [ "$extras" = dev ] && ! command -v chromium >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
      || echo "warning: could not install chromium; browser tests will be skipped" >&2
  else
    echo "note: install chromium to run the browser tests (they are skipped without it)" >&2
  fi
fi
