#!/usr/bin/env bash
# Several time-to-quality runs in one device call, one after another (never side by side: they
# would share the GPU). Usage on the GPU machine:
#   CHECKPOINTS=30,60 bash tools/ttq_runs.sh "LABEL ARGS..." ["LABEL ARGS..." ...]
# Each argument is a label then benchmarks.time_to_quality options (--method defaults to ours).
# The run in progress writes $OUT/ttq/LABEL.json (after every checkpoint) and LABEL.log; each
# finished run moves into $OUT/ttq.tgz, so a call cut short keeps every curve within the device's
# limit on returned files. A summary line per run is printed.
source tools/gpu_env.sh >/dev/null
OUT=${OUT:-/tmp/ttq_runs}; mkdir -p "$OUT/ttq"
done_dir=$(mktemp -d); mkdir -p "$done_dir/ttq"
for spec in "$@"; do
  read -r label args <<<"$spec"
  [[ $args == *--method* ]] || args="--method ours $args"
  # shellcheck disable=SC2086
  python -m benchmarks.time_to_quality --label "$label" --checkpoints "${CHECKPOINTS:-30,60,120,240}" \
    --out "$OUT/ttq" $args >"$OUT/ttq/$label.log" 2>&1
  echo "$label rc=$? $(grep -o '"seconds": [0-9.]*\|"val_psnr": [0-9.]*\|"rays": [0-9]*' "$OUT/ttq/$label.log" | tr '\n' ' ')"
  mv "$OUT/ttq/$label".* "$done_dir/ttq/" && tar czf "$OUT/ttq.tgz" -C "$done_dir" ttq
done
