#!/usr/bin/env bash
# Several time-to-quality runs in one device call. Usage on the GPU machine:
#   CHECKPOINTS=30,60 bash tools/ttq_runs.sh "LABEL ARGS..." ["LABEL ARGS..." ...]
# Each argument is a label then benchmarks.time_to_quality options (--method defaults to ours).
# One after another on one GPU (never side by side: they would share it); with GPUS=0,1,2,3 side
# by side, run k alone on GPU k (at most one run per GPU), each into its own folder
# $OUT/time_to_quality_gpu<k>/ (merge them with python -m benchmarks.plot_time_to_quality --add).
# Each run goes into its scene's file in $OUT/time_to_quality/ (<scene>_<device>.json) after every
# checkpoint, replacing a run of its label; the file starts as $RESULTS' (default
# benchmarks/results/time_to_quality, the current record; empty for a screen of its own), and only
# the files the runs write are copied (the device returns at most 8 files): copy the returned files
# back over $RESULTS and plot them (python -m benchmarks.plot_time_to_quality).
# Logs go to $OUT/ttq_logs.tgz as runs end (one after another) or once all have (side by side), so
# a call keeps within the device's limit on returned files. A summary line per run.
# $DEADLINE (seconds from this script's start; one after another only): curves longer than a call
# go through one queue over several calls. A run with --run-dir whose saved curve already holds
# every checkpoint is skipped, the next one resumed with --stop-after +(what is left, less
# $RUN_MARGIN, default 60 s for loading and validation), and no run starts with under twice that left;
# repeat the same call, the run folders carried, until every run is done.
source tools/gpu_env.sh >/dev/null
OUT=${OUT:-/tmp/ttq_runs}; mkdir -p "$OUT/time_to_quality"
RESULTS=${RESULTS-benchmarks/results/time_to_quality}
logs=$(mktemp -d)/logs; mkdir -p "$logs"
run() {  # run SPEC OUT_DIR
  local label args; read -r label args <<<"$1"
  [[ $args == *--method* ]] || args="--method ours $args"
  [ -n "$RESULTS" ] && [ -z "$GPUS" ] && args="$args --record-from $RESULTS"
  mkdir -p "$2"
  # shellcheck disable=SC2086
  python -m benchmarks.time_to_quality --label "$label" --checkpoints "${CHECKPOINTS:-30,60,120,240}" \
    --out "$2" $args >"$logs/$label.log" 2>&1
  echo "$label rc=$? $(grep -o '"seconds": [0-9.]*\|"val_psnr": [0-9.]*\|"rays": [0-9]*' "$logs/$label.log" | tr '\n' ' ')"
}
pack_logs() { tar czf "$OUT/ttq_logs.tgz" -C "$(dirname "$logs")" logs; }
finished() {  # finished ARGS: the run's --run-dir holds a curve of all its checkpoints
  local dir checkpoints=${CHECKPOINTS:-30,60,120,240}
  [[ $1 =~ --run-dir[=\ ]([^ ]+) ]] || return 1
  dir=${BASH_REMATCH[1]}
  [[ $1 =~ --checkpoints[=\ ]([^ ]+) ]] && checkpoints=${BASH_REMATCH[1]}
  python -c 'import json, sys; sys.exit(len(json.load(open(sys.argv[1]))["curve"]) < int(sys.argv[2]))' \
    "$dir/ttq_state.json" "$(tr ',' '\n' <<<"$checkpoints" | wc -l)" 2>/dev/null
}
if [ -z "$GPUS" ]; then
  margin=${RUN_MARGIN:-60}
  for spec in "$@"; do
    if [ -n "$DEADLINE" ]; then
      finished "$spec" && { echo "${spec%% *}: done in an earlier call"; continue; }
      left=$((DEADLINE - SECONDS))
      [ "$left" -lt $((2 * margin)) ] && { echo "${spec%% *}: not started, ${left}s left"; continue; }
      [[ $spec == *--run-dir* ]] && spec="$spec --stop-after +$((left - margin))"  # else it runs whole
    fi
    run "$spec" "$OUT/time_to_quality"; pack_logs
  done
else
  IFS=, read -ra gpus <<<"$GPUS"
  [ $# -le ${#gpus[@]} ] || { echo "ttq_runs.sh: $# runs for ${#gpus[@]} GPUs (one run per GPU)"; exit 2; }
  k=0
  for spec in "$@"; do
    CUDA_VISIBLE_DEVICES=${gpus[k]} run "$spec" "$OUT/time_to_quality_gpu$k" & k=$((k + 1))
  done
  wait
  pack_logs
fi
