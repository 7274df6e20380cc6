#!/usr/bin/env bash
# A sweep on one lent GPU machine through the Ray backend (benchmarks/bench_gpu_sweep.py): Ray's
# GPU placement, then how runs should share the GPU. One device call.
#
#   bash benchmarks/gpu_sweep_check.sh --prepare    # here: fills .device-sweep/ (git-ignored)
#   bash benchmarks/gpu_sweep_check.sh              # there, carrying .device-sweep; logs and JSON in $OUT
#
# The device has Python 3.12 and torch with CUDA but no registry. Ray's wheel alone is 79 MB and a
# call carries 64 MiB, so the packages travel unpacked into one xz archive (about 41 MB), with the
# parts of Ray a sweep never loads left out: its Java jars, the dashboard's web client, and the
# RLlib, Serve, Data, Train, Tune and LLM libraries. The methods' dataset travels installed (the
# device's h5py is not the pinned one, so a rebuild there would not match the manifest's sha256).
set -u
task=halfcheetah-friction-5.0
if [ "${1:-}" = "--prepare" ]; then
  set -e
  grep -qx /.device-sweep/ .git/info/exclude 2>/dev/null || echo /.device-sweep/ >> .git/info/exclude
  work=$(mktemp -d)
  bash scripts/device_wheels.sh "$work/wheels" ray==2.60.0 jsonschema==4.26.0 jsonschema-specifications==2025.9.1 \
    referencing==0.37.0 rpds-py==2026.9.1
  mkdir -p "$work/site" .device-sweep
  for wheel in "$work"/wheels/*.whl; do unzip -q -o "$wheel" -d "$work/site"; done
  (cd "$work/site/ray" && rm -rf jars dashboard/client/build rllib serve data train tune llm)
  tar -cJf .device-sweep/site.tar.xz -C "$work/site" .
  rm -rf "$work"
  dataset=$(.venv/bin/offdyn-bench datasets download --task "$task" --print-id)
  rm -rf .device-sweep/datasets && mkdir -p ".device-sweep/datasets/$(dirname "$dataset")"
  cp -r "${MINARI_DATASETS_PATH:-$HOME/.minari/datasets}/$dataset" ".device-sweep/datasets/$(dirname "$dataset")/"
  du -sh .device-sweep
  exit 0
fi

out=${OUT:-/tmp/gpu-sweep-check}
mkdir -p "$out" /tmp/site
unset MUJOCO_GL  # 'egl' fails where the EGL libraries are missing; nothing here renders
export PYTHONUNBUFFERED=1
tar -xJf .device-sweep/site.tar.xz -C /tmp/site || exit 1
export PYTHONPATH=/tmp/site:$PWD MINARI_DATASETS_PATH=$PWD/.device-sweep/datasets
nproc
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
python3 -c "import torch, ray, mujoco, offdyn_bench, baselines; from offdyn_bench.versions import machine
print('torch', torch.__version__, 'ray', ray.__version__, 'mujoco', mujoco.__version__); print(machine('cuda')['cuda'])" || exit 1
timeout "${SWEEP_TIMEOUT:-480}" python3 benchmarks/bench_gpu_sweep.py --out /tmp/gpu-sweep \
  --sharing-steps "${SHARING_STEPS:-2000}" --json "$out/gpu-sweep.json" 2>&1 | grep -v -e WARNING -e Warning | tee "$out/gpu-sweep.log"
# The placement sweep's state file and one run's log: what each attempt recorded.
cp /tmp/gpu-sweep/placement/sweep.json "$out/placement-sweep.json" 2>/dev/null
cp /tmp/gpu-sweep/placement/logs/cql/$task/seed-0.log "$out/placement-cql-seed-0.log" 2>/dev/null
echo "== done"
