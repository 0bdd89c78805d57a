#!/usr/bin/env bash
# One-command setup for a fresh machine (Python >= 3.10 with venv; no root, no apt needed:
# open3d's missing libusb-1.0.so.0 is supplied by the libusb-package wheel at import time).
#   bash tools/dev.sh demo   install into .venv and run lidar-slam on sample_scans/ -> runs/sample
#   bash tools/dev.sh test   install with the test, cluster (Ray), pcap and rko extras (and
#                            ouster-sdk, without its pins: pyproject.toml says why) and run the
#                            test suite
#   bash tools/dev.sh lint   install with the test extra and run ruff (the rules: pyproject.toml)
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}
if [ ! -x "$VENV/bin/python" ]; then
  "$PYTHON" -m venv "$VENV"
  "$VENV/bin/python" -m pip install -q --upgrade pip
fi
cmd=${1:-demo}
shift || true
case "$cmd" in
  demo)
    "$VENV/bin/python" -m pip install -q -e .
    # bytecode now, as a non-editable pip install would (an editable one writes none when
    # PYTHONDONTWRITEBYTECODE is set, and then every run compiles ~80 modules from source)
    "$VENV/bin/python" -m compileall -q lidar_slam
    "$VENV/bin/lidar-slam" run sample_scans --out runs/sample --overwrite "$@"
    ;;
  test)
    "$VENV/bin/python" -m pip install -q -e ".[test,cluster,pcap,rko]"
    "$VENV/bin/python" -m pip install -q --no-deps "ouster-sdk==1.0.1"
    "$VENV/bin/python" -m pytest -q "$@"
    ;;
  lint)
    "$VENV/bin/python" -m pip install -q -e ".[test]"
    "$VENV/bin/ruff" check . "$@"
    ;;
  *)
    echo "usage: bash tools/dev.sh demo|test|lint [args...]" >&2
    exit 2
    ;;
esac
