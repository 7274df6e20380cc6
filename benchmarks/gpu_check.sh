#!/usr/bin/env bash
# The GPU checks of one lent device call, in one script (the lease is short; a second start costs
# minutes): the CUDA tests, then bench_gpu.py's update and whole-train benchmarks, the CUDA-graph
# update against its eager twin and as whole runs, then the reference methods side by side
# (seed-batched on CUDA against one seed per CPU core, all at once).
#
#   bash benchmarks/gpu_check.sh --prepare    # here: fills .whl/ and .device-data/ (both git-ignored)
#   bash benchmarks/gpu_check.sh              # there, carrying .whl and .device-data; logs and JSON in $OUT
#   ONLY="tests shared" bash benchmarks/gpu_check.sh   # some sections: tests shared updates graph methods
#
# The device has Python 3.12 and torch with CUDA but no registry, so the rest travels as wheels; what
# travels must stay under 64 MiB, so the Gymnasium-Robotics wheel loses the assets of the robots this
# suite does not use (Franka kitchen, the Fetch/hand meshes). The methods' target dataset travels
# installed: the device's h5py is not the pinned one, so a rebuild there would not match the
# manifest's sha256.
set -u
methods_task=halfcheetah-friction-5.0
if [ "${1:-}" = "--prepare" ]; then
  set -e
  mkdir -p .git/info .whl .device-data
  for d in /.whl/ /.device-data/; do grep -qx "$d" .git/info/exclude 2>/dev/null || echo "$d" >> .git/info/exclude; done
  bash scripts/device_wheels.sh .whl gymnasium-robotics==1.4.2 pettingzoo==1.27.0 stable-baselines3==2.9.2
  wheel=$(ls .whl/gymnasium_robotics-*.whl)
  tmp=$(mktemp -d)
  (cd "$tmp" && unzip -q "$OLDPWD/$wheel" && rm -rf gymnasium_robotics/envs/assets/kitchen_franka \
     gymnasium_robotics/envs/assets/stls && record=$(ls -d ./*.dist-info)/RECORD \
     && grep -v -e assets/kitchen_franka -e assets/stls "$record" > "$record.new" && mv "$record.new" "$record" \
     && rm "$OLDPWD/$wheel" && zip -qr -9 "$OLDPWD/$wheel" .)
  rm -rf "$tmp"
  # Installs (or verifies) the dataset, its messages on stderr, and prints its id.
  dataset=$(.venv/bin/offdyn-bench datasets download --task "$methods_task" --print-id)
  mkdir -p ".device-data/$(dirname "$dataset")"
  cp -r "${MINARI_DATASETS_PATH:-$HOME/.minari/datasets}/$dataset" ".device-data/$(dirname "$dataset")/"
  du -sh .whl .device-data
  exit 0
fi

out=${OUT:-/tmp/gpu-check}
sections=${ONLY:-tests shared updates graph methods}
for section in $sections; do
  case $section in tests|shared|updates|graph|methods) ;; *)
    echo "error: ONLY: unknown section '$section'; expected some of: tests shared updates graph methods" >&2; exit 2 ;;
  esac
done
want() { case " $sections " in *" $1 "*) return 0 ;; *) return 1 ;; esac; }
mkdir -p "$out"
unset MUJOCO_GL  # 'egl' fails where the EGL libraries are missing; nothing here renders
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
[ -d .device-data ] && export MINARI_DATASETS_PATH=$PWD/.device-data
nproc
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee "$out/nvidia-smi.txt"
python3 -c "import torch, mujoco, offdyn_bench, baselines; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'mujoco', mujoco.__version__)" || exit 1

want tests && echo "== CUDA tests" && timeout 180 python3 -m pytest -q -p no:cacheprovider tests/baselines/test_baselines_device.py 2>&1 | tee "$out/pytest-device.log" | tail -15

want shared && echo "== four CQL runs sharing the GPU: evaluations from a CPU copy of the policy vs on the GPU, vs all 20 seeds in one process" &&
timeout 300 python3 benchmarks/bench_shared_gpu.py --runs 4 --steps 2000 --rounds 1 --task "$methods_task" \
  --json "$out/bench-shared-gpu.json" 2>&1 | grep -v -e Warning -e installed

want updates && echo "== updates (ours eager/graphed vs SB3) and a whole train run on CUDA vs one CPU core" &&
timeout 150 python3 benchmarks/bench_gpu.py --rounds 3 --updates-per-round 300 --train-seeds 5 --train-cpu-seeds 1 \
  --train-steps 2500 --json "$out/bench-updates.json" 2>&1 | tee "$out/bench-updates.log" | grep -v Warning

want graph && echo "== the graph update against its eager twin (must stay bit-identical and finite), then whole runs" &&
timeout 120 python3 benchmarks/graph_soak.py --seeds 1 20 --twin-updates 3000 --soak 30000 \
  --json "$out/graph-soak.json" 2>&1 | grep -v Warning | tail -6
want graph && timeout 150 python3 benchmarks/bench_cuda_graph.py --methods cql sac-target --task "$methods_task" --steps 2000 \
  --seeds 5 --rounds 2 --json "$out/bench-cuda-graph.json" 2>&1 | grep -v -e Warning -e "official offline" -e installed

want methods && echo "== reference methods, 5 seeds on CUDA vs one seed per CPU core, all at once" &&
timeout "${METHODS_TIMEOUT:-210}" python3 benchmarks/bench_gpu.py --seeds --skip-sb3 --train-seeds 0 \
  --methods sac-target cql darc h2o dap dap-u --methods-task "$methods_task" --methods-steps "${METHODS_STEPS:-1500}" \
  --json "$out/bench-methods.json" 2>&1 | tee "$out/bench-methods.log" | grep -v Warning
echo "== done"
