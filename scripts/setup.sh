#!/usr/bin/env bash
# Set up dm2 in ./.venv: the Debian package open3d needs, then dm2 and its Python dependencies.
# Usage: bash scripts/setup.sh [--dev]   (--dev adds the test and lint tools and the optional back-ends)
set -euo pipefail
cd "$(dirname "$0")/.."

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    if [ "$(id -u)" = 0 ]; then
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
    elif command -v sudo >/dev/null; then
        sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
    else
        echo "setup: open3d needs the Debian package libusb-1.0-0; install it and rerun" >&2
        exit 1
    fi
fi

PYTHON="${PYTHON:-python3}"
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
extras=""
[ "${1:-}" = "--dev" ] && extras="[dev]"
# torch is pinned to the CPU build (2.13.0) in pyproject.toml; an unpinned torch would pull a CUDA build.
.venv/bin/pip install --quiet --disable-pip-version-check -e ".${extras}" 2>&1 | grep -v "^WARNING: Location" || true
.venv/bin/python -c "import dm2_backend, open3d, torch, gtsam, evo, rosbags" \
    || { echo "setup: dm2 did not install" >&2; exit 1; }
echo "setup: ready: dm2 is installed in .venv, not on your PATH: run \`source .venv/bin/activate\` (then \`dm2 ...\`), or call .venv/bin/dm2"
