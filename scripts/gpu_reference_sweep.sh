#!/usr/bin/env bash
# Reference runs on a lent GPU machine, inside the few minutes a lease gives (README, "Devices").
#
#   bash scripts/gpu_reference_sweep.sh --prepare METHOD lite|STEPS TASK...   # here: fills .device-sweep/
#   bash scripts/gpu_reference_sweep.sh [WAIT_S]                              # there, carrying .device-sweep
#
# --prepare writes a sweep spec (METHOD on each TASK, seeds 0-4, or SEEDS=1,2,3,4, trained together in
# one CUDA run per task, on the official target dataset or, DATASETS=medium,..., on each of those
# qualities, the offline-target track, the lite budget or STEPS steps for a smoke test; SAC and CQL replay
# their update from a CUDA graph, which computes what the eager update does), the Python 3.12 wheels
# the device lacks, and each task's installed target dataset (the device's h5py is not the pinned
# one, so a rebuild there would not match the manifest's sha256). What travels must stay under
# 64 MiB: the wheels take about 26 MB, a core task's dataset about 3 MB packed (an H2O setting's medium
# data about 16 MB). Processes on one GPU take
# turns, so more tasks do not finish sooner: a lease finishes about two lite CQL tasks (measured
# twice: README, Devices). RESUME_FROM=<a folder of the partial.*.tar a call brought back>
# adds the runs that lease cut short (its partial.*.tar files, checked against the spec), which the
# sweep there resumes from their checkpoints; each takes about 15 MB of the 64 MiB for 5 CQL seeds.
# ADD=1 --prepare ... adds a group to the prepared folder (spec-2.yaml, its own sweep and out
# gpu-reference-2, its datasets beside the first group's wheels), for runs one spec cannot hold.
#
# There, each group's sweep (local backend, one worker per run) starts in its own process session, so it
# outlives the call; a second call made at once (before the machine's idle release) finds it and
# only waits. Each call returns when the sweep ends or after WAIT_S seconds (default 540), with
# the finished runs, checkpoints left out, in $OUT/sweep.tar.xz, the sweep's log, its status table
# (each run's steps and the share of its time its evaluations took) and the GPU's load, sampled once
# a minute ($OUT/gpu.log); and each unfinished run with its newest checkpoint, most advanced first,
# as far as what a call brings back allows ($OUT/partial.<method>.<task>.<seeds>.tar). Then here:
#
#   bash scripts/gpu_reference_sweep.sh --collect <files_at>     # after each call, before the next
#
# --collect files each unfinished run's archive by its group (runs/cut-short/group-N, what
# RESUME_FROM takes next lease; one a later call finished is dropped), unpacks the finished runs
# into runs/lease-<time>/ and publishes each group's (offdyn-bench leaderboard publish-runs).
set -u
# DEVICE_SWEEP_DIR and SWEEP_ROOT move the two folders (tests/test_gpu_reference_sweep.py does).
dir=${DEVICE_SWEEP_DIR:-.device-sweep}
sweep_root=${SWEEP_ROOT:-/tmp/offdyn-gpu-reference}
# A group's suffix from its spec file (spec.yaml -> "", spec-2.yaml -> -2); the run ids in a sweep's
# dry run; those of a spec (here only: the device has no .venv); a cut-short run's archive name, as
# scripts/pack_unfinished_runs.py writes it.
suffix_of() { local name; name=$(basename "$1" .yaml); echo "${name#spec}"; }
run_ids() { awk '/^[^ ]+\/[^ ]+\/[^ ]+ \(/ {print $1}'; }
spec_run_ids() {
  local scratch; scratch=$(mktemp -d)
  .venv/bin/offdyn-bench sweep "$1" --dry-run --out "$scratch/out" 2>/dev/null | run_ids
  rm -rf "$scratch"
}
archive_of() { echo "partial.${1//\//.}.tar"; }
if [ "${1:-}" = "--collect" ]; then
  # Here, after each call: files what the call brought back before the next call replaces it.
  set -e
  from=${2:-} runs_dir=${3:-runs}
  if [ -z "$from" ] || [ ! -d "$from" ]; then
    echo "usage: $0 --collect FILES_AT [RUNS_DIR] (FILES_AT: the folder a lease call's files came back to; RUNS_DIR default runs)" >&2
    exit 2
  fi
  partials=("$from"/partial.*.tar)
  if [ ! -f "$from/sweep.tar.xz" ] && [ ! -f "${partials[0]}" ]; then
    echo "error: $from holds neither sweep.tar.xz nor partial.*.tar (what a lease call brings back)" >&2
    exit 2
  fi
  [ -f "$dir/spec.yaml" ] || { echo "error: no $dir/spec.yaml: --collect files the runs by the groups --prepare made; run it where --prepare ran" >&2; exit 2; }
  # The unfinished runs first, each into its group's folder (what RESUME_FROM takes next lease).
  declare -A filed=()
  for spec in "$dir"/spec*.yaml; do
    group=$(suffix_of "$spec") && group=${group#-} && group=${group:-1}
    for id in $(spec_run_ids "$spec"); do
      name=$(archive_of "$id")
      [ -f "$from/$name" ] || continue
      mkdir -p "$runs_dir/cut-short/group-$group" && cp "$from/$name" "$runs_dir/cut-short/group-$group/"
      filed[$name]=1
      echo "kept: $name in $runs_dir/cut-short/group-$group (RESUME_FROM for group $group)"
    done
  done
  for archive in "${partials[@]}"; do
    [ -f "$archive" ] && [ -z "${filed[$(basename "$archive")]:-}" ] || continue
    mkdir -p "$runs_dir/cut-short" && cp "$archive" "$runs_dir/cut-short/"
    echo "warning: $(basename "$archive") is no run of $dir's groups: kept in $runs_dir/cut-short" >&2
  done
  if [ -f "$from/sweep.tar.xz" ]; then
    # Each call brings back every run finished so far: a folder per call, so none is mixed with
    # an earlier lease's.
    lease=$runs_dir/lease-$(date -u +%Y%m%dT%H%M%SZ)
    mkdir -p "$lease" && tar -xJf "$from/sweep.tar.xz" -C "$lease"
    for evaluation in "$lease"/*/runs/*/*/*/evaluation.json; do
      [ -f "$evaluation" ] || continue
      # A finished run's archive from an earlier call would resume what is done: dropped.
      id=$(awk -F/ '{print $(NF-3) "/" $(NF-2) "/" $(NF-1)}' <<< "$evaluation")
      for stale in "$runs_dir"/cut-short/group-*/"$(archive_of "$id")"; do
        [ -f "$stale" ] && rm "$stale" && echo "finished, so no longer kept: $stale"
      done
    done
    for root in "$lease"/gpu-reference*; do
      [ -d "$root" ] || continue
      echo "publishing $root"
      .venv/bin/offdyn-bench leaderboard publish-runs "$root" ${PUBLISH_TO:+--to "$PUBLISH_TO"}
    done
  fi
  exit 0
fi
if [ "${1:-}" = "--prepare" ]; then
  set -e
  if [ $# -lt 4 ]; then
    echo "usage: $0 --prepare METHOD lite|STEPS TASK... (e.g. --prepare cql lite hopper-gravity-0.5)" >&2
    exit 2
  fi
  method=$2 budget=$3
  shift 3
  case $budget in
    lite) budget_line="budget: lite" ;;
    *[!0-9]*|"") echo "error: budget $budget: expected lite or a number of steps" >&2; exit 2 ;;
    *) budget_line="steps: $budget" ;;
  esac
  # SEEDS: the training seeds, all in one run per task (seeds a CPU session published already stay
  # out: the dry run below refuses a run that would train them again). DATASETS: the target dataset
  # qualities of the H2O paper's Table 1 (one run per task and quality, as in
  # examples/sweeps/h2o-table1-lite.yaml); unset, the track's official dataset.
  seeds=${SEEDS:-0,1,2,3,4} qualities=${DATASETS:-}
  case ",$seeds," in
    *[!0-9,]*|*,,*) echo "error: SEEDS=$seeds: expected training seeds separated by commas, e.g. SEEDS=1,2,3,4" >&2
                    exit 2 ;;
  esac
  case ",$qualities," in
    *[!a-z,-]*|*,,*) [ -z "$qualities" ] || { echo "error: DATASETS=$qualities: expected dataset qualities separated by commas, e.g. DATASETS=medium,medium-replay" >&2; exit 2; } ;;
  esac
  n_seeds=$(tr ',' '\n' <<< "$seeds" | wc -l)
  n_datasets=$(tr ',' '\n' <<< "${qualities:-official}" | wc -l)
  n_runs=$(( $# * n_datasets ))
  if [ "$dir" = .device-sweep ]; then  # kept out of git (and so out of what travels unless carried)
    grep -qxF '/.device-sweep*/' .git/info/exclude 2>/dev/null || echo '/.device-sweep*/' >> .git/info/exclude
  fi
  # Built beside the folder and moved into place at the end: a failed prepare leaves the last
  # good one as it was.
  final=$dir dir=$dir.partial
  trap 'rm -rf "$dir"' EXIT
  rm -rf "$dir"
  # ADD=1 adds a group (its own spec, sweep and out) to a prepared folder, so runs that one spec
  # cannot hold share a lease: an H2O setting's medium cell beside a core task, say. Group 1 keeps
  # the plain names (spec.yaml, gpu-reference); group N adds -N.
  if [ "${ADD:-0}" = 1 ]; then
    [ -f "$final/spec.yaml" ] || { echo "error: ADD=1: no prepared $final/spec.yaml to add a group to; prepare the first group without ADD" >&2; exit 2; }
    cp -a "$final" "$dir"
    group=$(( $(ls "$dir"/spec*.yaml | wc -l) + 1 )) && sfx=-$group
  else
    group=1 sfx=""
  fi
  mkdir -p "$dir/wheels" "$dir/datasets"
  spec=$dir/spec$sfx.yaml
  # The spec and its dry run first: a wrong task, quality or seed, or runs published already, are
  # refused before minutes go into wheels and datasets.
  tasks=$(printf '%s, ' "$@") tasks=${tasks%, }
  device=${DEVICE:-cuda}  # DEVICE=cpu: the same flow checked on a machine without a GPU
  # The reference grid's own settings for the method (DARC's correction from step 10,000 at lite),
  # so that the lease trains the grid's runs; none at other budgets.
  settings=""
  if [ "$budget" = lite ]; then
    settings=$(.venv/bin/python - "$method" <<'PY'
import json, sys
from offdyn_bench.sweep.spec import load_spec
spec = load_spec("examples/sweeps/reference-lite.yaml")
print(", ".join(f"{key}: {json.dumps(value)}" for key, value in spec.overrides.get(sys.argv[1], {}).items()))
PY
) || exit 2
  fi
  # The methods with a graph update are those whose config takes cuda_graph (an unknown method
  # takes none here and fails the dry run below, with its own message).
  if [ "$device" = cuda ] && .venv/bin/offdyn-bench train "$method" --print-config --set cuda_graph=true \
      >/dev/null 2>&1; then
    settings="${settings:+$settings, }cuda_graph: \"true\""
  fi
  overrides=""
  [ -n "$settings" ] && overrides="overrides: {$method: {$settings}}"
  cat > "$spec" <<EOF
methods: [$method]
tasks: [$tasks]
seeds: [${seeds//,/, }]
seeds_per_run: $n_seeds
${qualities:+datasets: [${qualities//,/, }]}
track: offline-target
$budget_line
out: $sweep_root/gpu-reference$sfx
device: $device
max_retries: 1
$overrides
EOF
  # The device parses the spec with the same code: an unknown method or setting fails here, now. At
  # lite the same dry run marks the runs whose records are published already: a lease is too short
  # to spend on them.
  skip_published=""
  [ "$budget" = lite ] && skip_published=--skip-published
  dry_run=$(.venv/bin/offdyn-bench sweep "$spec" --dry-run $skip_published --out "$dir/dry-run") || exit 2
  rm -rf "$dir/dry-run"
  published=$(printf '%s\n' "$dry_run" | sed -n 's|^\([^ ]*\) (published: skipped.*|\1|p')
  if [ -n "$published" ]; then
    echo "error: published already (leaderboard/reference-runs/lite), leave out their tasks:" $published >&2
    exit 2
  fi
  # A group may not train a (method, task, dataset) cell that another group trains: both could not
  # be published, since a training seed is published once.
  cells() { awk -F/ '{ data = $3; if (data ~ /\./) sub(/\.[^.]*$/, "", data); else data = ""
                      print $1 "/" $2 (data == "" ? "" : " (" data ")") }' | sort -u; }
  for other in "$dir"/spec*.yaml; do
    [ "$other" != "$spec" ] || continue
    both=$(comm -12 <(spec_run_ids "$other" | cells) <(printf '%s\n' "$dry_run" | run_ids | cells))
    if [ -n "$both" ]; then
      echo "error: ADD=1: $(basename "$other") trains these already, and a seed is published once:" $both >&2
      exit 2
    fi
  done
  if [ -n "${RESUME_FROM:-}" ]; then
    # Runs an earlier lease cut short (its partial.*.tar files) resume here from their checkpoints;
    # checked before the wheels and datasets, so a wrong folder costs no time.
    archives=("$RESUME_FROM"/partial.*.tar)
    [ -f "${archives[0]}" ] || { echo "error: RESUME_FROM=$RESUME_FROM holds no partial.*.tar (what a lease call brings back)" >&2; exit 2; }
    .venv/bin/python scripts/pack_unfinished_runs.py --check "$spec" "${archives[@]}" || exit 2
    mkdir -p "$dir/partial$sfx" && cp "${archives[@]}" "$dir/partial$sfx/"
    echo "resumes: $(basename -a "${archives[@]}" | tr '\n' ' ')"
  fi
  # SKIP_WHEELS=1: no wheels (a check of this script where the packages are installed).
  # An added group's payload holds its datasets only: the first group's wheels serve every group.
  [ "${SKIP_WHEELS:-0}" = 1 ] || [ "$group" != 1 ] || bash scripts/device_wheels.sh "$dir/wheels"
  for task in "$@"; do
    # Installs (or verifies) each dataset, its messages on stderr, and prints its id.
    for quality in $(tr ',' ' ' <<< "${qualities:-official}"); do
      choice=()
      [ "$quality" = official ] || choice=(--quality "$quality")
      dataset=$(.venv/bin/offdyn-bench datasets download --task "$task" "${choice[@]}" --print-id)
      mkdir -p "$dir/datasets/$(dirname "$dataset")"
      cp -r "${MINARI_DATASETS_PATH:-$HOME/.minari/datasets}/$dataset" "$dir/datasets/$(dirname "$dataset")/"
    done
  done
  echo "$n_runs" > "$dir/workers$sfx"
  all_runs=$(( $(cat "$dir"/workers* | paste -sd+) ))
  if [ "$budget" = lite ] && [ "$all_runs" -gt 2 ] && grep -q '^methods: \[cql\]$' "$dir"/spec*.yaml; then
    # Measured on an H200: four lite CQL tasks at once stood at 25-45% after 9 minutes; two
    # finished in about 11 minutes.
    echo "note: $all_runs lite runs, CQL among them: the measured lease would finish about two lite CQL runs (README, Devices); the rest come back unfinished" >&2
  fi
  # One xz archive: the datasets shrink about 3x, so more tasks fit in what a call carries.
  tar -cJf "$dir/payload$sfx.tar.xz" -C "$dir" wheels datasets && rm -rf "$dir/wheels" "$dir/datasets"
  cat "$spec"
  tracked=$(git ls-files -z | xargs -0 du -cb 2>/dev/null | tail -1 | cut -f1)
  carried=$(du -sb "$dir" | cut -f1)
  echo "travels: $(( (tracked + carried) / 1048576 )) MiB of 64 (tracked $(( tracked / 1048576 )), $final $(( carried / 1048576 )))"
  [ $(( tracked + carried )) -lt $(( 64 * 1048576 )) ] || { echo "error: over 64 MiB: prepare fewer tasks" >&2; exit 1; }
  rm -rf "$final" && mv "$dir" "$final"
  exit 0
fi

wait_s=${1:-540}
out=${OUT:-$sweep_root/out}
[ -f "$dir/spec.yaml" ] || { echo "error: no $dir/spec.yaml: run --prepare here first and carry $dir" >&2; exit 2; }
mkdir -p "$out" "$sweep_root"
unset MUJOCO_GL  # 'egl' fails where the EGL libraries are missing; nothing here renders
export PYTHONUNBUFFERED=1
payload=$sweep_root/payload
if [ ! -f "$payload/.installed" ]; then
  mkdir -p "$payload"
  for archive in "$dir"/payload*.tar.xz; do tar -xJf "$archive" -C "$payload" || exit 1; done
  # Where the packages are already installed (a check of this script here), the wheels are not.
  python3 -c "import mujoco, gymnasium, minari" 2>/dev/null \
    || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$payload/site" \
         "$payload"/wheels/*.whl || exit 1
  touch "$payload/.installed"
fi
export PYTHONPATH=$payload/site:$PWD MINARI_DATASETS_PATH=$payload/datasets
# Group 1's spec.yaml, then any groups ADD=1 prepared (spec-2.yaml, ...), each its own sweep:
# sweep<sfx>.pid, sweep<sfx>.log, gpu-reference<sfx>.
specs=("$dir/spec.yaml")
for spec in "$dir"/spec-*.yaml; do [ -f "$spec" ] && specs+=("$spec"); done
running() { [ -f "$sweep_root/sweep$1.pid" ] && kill -0 "$(cat "$sweep_root/sweep$1.pid")" 2>/dev/null; }
any_running() { local spec; for spec in "${specs[@]}"; do running "$(suffix_of "$spec")" && return 0; done; return 1; }
shown=0
for spec in "${specs[@]}"; do
  sfx=$(suffix_of "$spec") root=$sweep_root/gpu-reference$sfx
  if running "$sfx"; then
    echo "the sweep of $(basename "$spec") started by an earlier call is still running (pid $(cat "$sweep_root/sweep$sfx.pid")): waiting for it"
    continue
  fi
  if [ $shown = 0 ]; then
    shown=1
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null
    python3 -c "import torch, mujoco; print('torch', torch.__version__, 'mujoco', mujoco.__version__)" || exit 1
  fi
  for archive in "$dir/partial$sfx"/*.tar; do
    [ -f "$archive" ] || continue
    # A run an earlier lease cut short, unless this machine has it already (a later call).
    run=$(tar -tf "$archive" | awk -F/ '$4 != "" {print $1 "/" $2 "/" $3 "/" $4; exit}')
    [ -d "$root/$run" ] || { mkdir -p "$root" && tar -xf "$archive" -C "$root" && echo "resuming $run from the archive"; }
  done
  # A sweep resumes its unfinished runs from their checkpoints, so starting again is safe.
  setsid nohup python3 -m offdyn_bench sweep "$spec" --workers "$(cat "$dir/workers$sfx")" \
    >> "$sweep_root/sweep$sfx.log" 2>&1 < /dev/null &
  echo $! > "$sweep_root/sweep$sfx.pid"
done
deadline=$(( SECONDS + wait_s ))
sampled=$(( SECONDS - 60 ))  # the first sample at once
while any_running && [ $SECONDS -lt $deadline ]; do
  # Once a minute, how busy the GPU is: a busy GPU and slow runs mean the updates are the limit.
  if [ $(( SECONDS - sampled )) -ge 60 ]; then
    sampled=$SECONDS
    nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader 2>/dev/null \
      | sed "s/^/$(date -u +%H:%M:%S) GPU busy, memory: /" >> "$sweep_root/gpu.log"
  fi
  sleep 5
done
if any_running; then
  echo "still running after ${wait_s} s: call again at once (the machine keeps it for its idle release only)"
else
  echo "the sweep has ended"
fi
roots=()
for spec in "${specs[@]}"; do
  sfx=$(suffix_of "$spec")
  tr '\r' '\n' < "$sweep_root/sweep$sfx.log" | grep -v -e Warning -e "^ *logger" | tail -3
  # Each run's steps, the share of its time its evaluations took, its compute: what a lease measured.
  python3 -m offdyn_bench sweep "$spec" --status 2>&1 | grep -v Warning
  cp "$sweep_root/sweep$sfx.log" "$out/sweep$sfx.log"
  [ -d "$sweep_root/gpu-reference$sfx" ] && roots+=("gpu-reference$sfx")
done
[ -s "$sweep_root/gpu.log" ] && tail -4 "$sweep_root/gpu.log" && cp "$sweep_root/gpu.log" "$out/gpu.log"
[ ${#roots[@]} -gt 0 ] && tar -cJf "$out/sweep.tar.xz" -C "$sweep_root" --exclude=checkpoints "${roots[@]}"
# Unfinished runs come back too, each with its newest checkpoint, within what a call brings back
# (8 files of at most 16 MiB, 64 MiB in all): kept in a folder here, RESUME_FROM=<it> --prepare sends them
# to the next lease.
for root in "${roots[@]}"; do
  files=$(ls -A "$out" | wc -l) bytes=$(du -sb "$out" | cut -f1)
  python3 scripts/pack_unfinished_runs.py "$sweep_root/$root" "$out" --max-files $(( 8 - files )) \
    --max-bytes $(( 63 * 1048576 - bytes ))
done
ls -la "$out"
