#!/usr/bin/env bash
# Train the behaviour policies the source-policy datasets use ("RL on source": SAC in the source
# dynamics, DAP Section 5.1) with the baselines' SAC, then import one seed's actor of each into
# assets/policies/sac-source/<dynamics>.safetensors (+ .json sidecar with config and score).
#
#   bash assets/policies/train_behaviour_policies.sh RUNS_DIR STEPS [WALL_SECONDS]
#
# All runs go in parallel, one CPU thread each. With WALL_SECONDS > 0 each run is stopped after
# that long and its latest complete checkpoint is imported (the sidecar records which step it
# reached). NAMES="hopper-nominal ant-nominal" restricts the set; CHECKPOINT_EVERY sets the
# checkpoint interval (default STEPS/40).
set -euo pipefail
RUNS=${1:?usage: train_behaviour_policies.sh RUNS_DIR STEPS [WALL_SECONDS]}
STEPS=${2:?steps}
WALL=${3:-0}
PY=${PYTHON:-python3}
OUT_DIR=${POLICY_DIR:-assets/policies/sac-source}

# policy (named by its training dynamics) -> a task whose source has exactly those dynamics
declare -A TASK_OF=(
  [hopper-nominal]=hopper-gravity-0.5
  [halfcheetah-nominal]=halfcheetah-gravity-0.5
  [walker2d-nominal]=walker2d-gravity-0.5
  [ant-nominal]=ant-gravity-0.5
  [halfcheetah-h2o-gravity-2.0-source]=halfcheetah-h2o-gravity-2.0
  [halfcheetah-h2o-friction-0.3-source]=halfcheetah-h2o-friction-0.3
  [halfcheetah-h2o-joint-noise-1.0-source]=halfcheetah-h2o-joint-noise-1.0
  [walker2d-h2o-gravity-2.0-source]=walker2d-h2o-gravity-2.0
  [walker2d-h2o-friction-0.3-source]=walker2d-h2o-friction-0.3
  [walker2d-h2o-joint-noise-1.0-source]=walker2d-h2o-joint-noise-1.0
)
NAMES=${NAMES:-${!TASK_OF[@]}}

mkdir -p "$RUNS" "$OUT_DIR"
for name in $NAMES; do
  task=${TASK_OF[$name]}
  cmd=("$PY" -m baselines train sac-source --task "$task" --steps "$STEPS" --out "$RUNS/$name" --seed 0
       --threads 1 --no-progress --eval-every "$STEPS" --checkpoint-every "${CHECKPOINT_EVERY:-$((STEPS / 40 > 0 ? STEPS / 40 : 1))}")
  if [ "$WALL" -gt 0 ]; then
    (timeout "$WALL" "${cmd[@]}" >"$RUNS/$name.log" 2>&1 || echo "$name stopped after ${WALL}s (rc $?)" >>"$RUNS/$name.log") &
  else
    "${cmd[@]}" >"$RUNS/$name.log" 2>&1 &
  fi
done
wait

for name in $NAMES; do
  task=${TASK_OF[$name]}
  env_id=$("$PY" -c "import offdyn_bench; print(offdyn_bench.get_task('$task').env_id('source'))")
  "$PY" -m offdyn_bench datasets import-policy "$RUNS/$name" --trained-on "$env_id" \
    --out "$OUT_DIR/$name.safetensors" >>"$RUNS/$name.log" 2>&1 &
done
wait
for name in $NAMES; do tail -n 1 "$RUNS/$name.log"; done
