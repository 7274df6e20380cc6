#!/usr/bin/env bash
# The wheels a lent GPU machine lacks: it runs Python 3.12 with torch preinstalled and reaches no
# package registry, so they are downloaded here and carried.
#
#   bash scripts/device_wheels.sh DIR [PACKAGE==VERSION...]
#
# Downloads the simulator stack (the versions pyproject.toml pins) and any further packages into
# DIR, for Python 3.12 on manylinux x86_64, without dependencies (the list is the whole set).
# Used by benchmarks/gpu_check.sh, benchmarks/gpu_sweep_check.sh and scripts/gpu_reference_sweep.sh.
set -eu
if [ $# -lt 1 ]; then
  echo "usage: $0 DIR [PACKAGE==VERSION...]" >&2
  exit 2
fi
dir=$1
shift
mkdir -p "$dir"
for pkg in mujoco==3.17.0 gymnasium==1.4.0 minari==0.5.4 glfw==2.11.0 farama-notifications==0.0.6 "$@"; do
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 -d "$dir" "$pkg"
done
