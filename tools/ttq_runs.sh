#!/usr/bin/env bash
# Several time-to-quality runs in one device call, one after another (never side by side: they
# would share the GPU). Usage on the GPU machine:
#   CHECKPOINTS=30,60 bash tools/ttq_runs.sh "LABEL ARGS..." ["LABEL ARGS..." ...]
# Each argument is a label then benchmarks.time_to_quality options (--method defaults to ours).
# The runs files of $RESULTS (default benchmarks/results/time_to_quality, the current record; empty
# for a screen of its own) are copied to $OUT/time_to_quality/ first, and each run goes into its
# scene's file there (<scene>_<device>.json) after every checkpoint, replacing a run of its label:
# copy the returned files back over $RESULTS and plot them (python -m benchmarks.plot_time_to_quality).
# The run in progress logs to $OUT/LABEL.log; finished logs move into $OUT/ttq_logs.tgz, so a call
# cut short keeps every curve within the device's limit on returned files. A summary line per run.
source tools/gpu_env.sh >/dev/null
OUT=${OUT:-/tmp/ttq_runs}; mkdir -p "$OUT/time_to_quality"
RESULTS=${RESULTS-benchmarks/results/time_to_quality}
[ -n "$RESULTS" ] && cp "$RESULTS"/*.json "$OUT/time_to_quality/"
done_dir=$(mktemp -d); mkdir -p "$done_dir/logs"
for spec in "$@"; do
  read -r label args <<<"$spec"
  [[ $args == *--method* ]] || args="--method ours $args"
  # shellcheck disable=SC2086
  python -m benchmarks.time_to_quality --label "$label" --checkpoints "${CHECKPOINTS:-30,60,120,240}" \
    --out "$OUT/time_to_quality" $args >"$OUT/$label.log" 2>&1
  echo "$label rc=$? $(grep -o '"seconds": [0-9.]*\|"val_psnr": [0-9.]*\|"rays": [0-9]*' "$OUT/$label.log" | tr '\n' ' ')"
  mv "$OUT/$label.log" "$done_dir/logs/" && tar czf "$OUT/ttq_logs.tgz" -C "$done_dir" logs
done
