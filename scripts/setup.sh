#!/usr/bin/env bash
# Set up beadsight in ./.venv. Usage: scripts/setup.sh [--dev]
#   (no flag)  the package with its hardware/export/ROS extras
#   --dev      also the test tools, and Debian's chromium for the browser tests
# torch is installed first and pinned: a bare "torch" requirement resolved from
# scratch pulls a multi-GB CUDA build, while torch==2.13.0 takes the local CPU build
# (on a CUDA machine the same pin installs the CUDA build).
# Every step must succeed: a failed install stops the script with pip's or apt's error.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
TORCH_SPEC=${BEADSIGHT_TORCH:-torch==2.13.0}
extras=all
[ "${1:-}" = "--dev" ] && extras=dev

# Debian's chromium for the browser tests: installed while uv installs the Python packages,
# and without its recommends (avahi, cups, GTK, perl...), which headless use does not need:
# 25 packages instead of 115, 10 s instead of 20 s here.
apt_pid=
trap wait EXIT  # a failed step still lets the background jobs finish (no apt left holding dpkg's lock)
if [ "$extras" = dev ] && ! command -v chromium >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    apt_log=$(mktemp)
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
      apt-get install -y -qq --no-install-recommends chromium) >"$apt_log" 2>&1 &
    apt_pid=$!
  else
    echo "note: install Debian's chromium to run the browser tests (under CI=true they fail without it)" >&2
  fi
fi

# uv installs the packages: pip asks the index about one package at a time, which took
# 3.5 min for torch alone on a clean machine; uv resolves and fetches in parallel (~30 s).
# The venv is made without pip (ensurepip alone took 28 s) when the system pip can put uv in
# it; uv then installs pip into it too, for users who want it.
if [ ! -x .venv/bin/python ]; then
  if "$PY" -m pip --version >/dev/null 2>&1; then "$PY" -m venv --without-pip .venv; else "$PY" -m venv .venv; fi
fi
if [ ! -x .venv/bin/uv ]; then
  # The system pip installs into the venv by --prefix (the venv's own Python): 3 s, where
  # --python .venv/bin/python starts a second pip inside the venv (5 s). Not where the prefix
  # layout is not the venv's (Debian's Python puts --prefix installs under local/). It
  # ignores what the system Python has installed, or a uv there would count as installed.
  if .venv/bin/python -m pip --version >/dev/null 2>&1; then
    pip=(.venv/bin/python -m pip install)
  elif [ "$("$PY" -c 'import sysconfig; print(sysconfig.get_preferred_scheme("prefix"))')" = posix_prefix ]; then
    pip=("$PY" -m pip install --prefix .venv --ignore-installed)
  else
    pip=("$PY" -m pip --python .venv/bin/python install)
  fi
  "${pip[@]}" -q --disable-pip-version-check "uv>=0.4" 2>&1 \
    | sed '/^WARNING: \(Location\|Running pip as\)/d'  # pip's status is kept (pipefail)
fi
# uv does not read pip's configuration, so pip's find-links (a local torch build) are passed on.
links=${UV_FIND_LINKS:-${PIP_FIND_LINKS:-}}
if [ -z "$links" ] && found=$("$PY" -m pip config get global.find-links 2>/dev/null); then
  links=$found
fi
uv_install() {
  UV_FIND_LINKS="$links" .venv/bin/uv pip install -q --python .venv/bin/python "$@"
}

.venv/bin/python -c "import torch" 2>/dev/null || uv_install "$TORCH_SPEC"
uv_install pip -e ".[$extras]"
# bytecode for what beadsight imports (uv compiles none): a second core's work while OctoPrint
# installs and chromium unpacks
warm_log=$(mktemp)  # its last line says what is ready
env -u PYTHONDONTWRITEBYTECODE .venv/bin/python scripts/warm_bytecode.py >"$warm_log" &
warm_pid=$!
collect_pid=
if [ "$extras" = dev ]; then  # the test modules' bytecode, their asserts rewritten: compiled
  # here beside the above, not by each of pytest's workers at once when the tests start
  collect_log=$(mktemp)
  env -u PYTHONDONTWRITEBYTECODE .venv/bin/python -m pytest --collect-only -q \
    -p no:cacheprovider >"$collect_log" 2>&1 &
  collect_pid=$!
fi
if [ "$extras" = dev ]; then  # OctoPrint's virtual printer, an independent Marlin peer for the
  # tests; OctoPrint pins many packages, so it gets a venv of its own (uv: seconds, not minutes)
  [ -x .venv-octoprint/bin/python ] || .venv/bin/uv venv -q -p "$PY" .venv-octoprint
  .venv/bin/uv pip install -q --python .venv-octoprint/bin/python "OctoPrint==1.11.8"
fi
if [ -n "$apt_pid" ] && ! wait "$apt_pid"; then
  cat "$apt_log" >&2
  echo "setup: installing Debian's chromium failed (above)" >&2
  exit 1
fi
wait "$warm_pid"
if [ -n "$collect_pid" ] && ! wait "$collect_pid"; then
  cat "$collect_log" >&2
  echo "setup: collecting the tests failed (above)" >&2
  exit 1
fi
cat "$warm_log"
