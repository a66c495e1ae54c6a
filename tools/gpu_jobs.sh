#!/usr/bin/env bash
# A queue of single-GPU jobs over the GPUs of one machine, one job per GPU at a time, in the order
# given, until the queue is empty or $DEADLINE seconds (default 560) have passed. Usage there:
#   GPUS=0,1,2,3 DEADLINE=560 bash tools/gpu_jobs.sh JOBS_FILE
# JOBS_FILE: one shell command per line, run from the repo root with CUDA_VISIBLE_DEVICES set to its
# GPU and $JOB_OUT (a folder of its own under $OUT/jobs) exported; '#' lines and blank lines are
# skipped. At the deadline running jobs get SIGTERM. A job that exits 0 is written to $DONE (default
# runs/gpu_jobs.done, kept on a warm machine), and a later call skips it: so a queue cut by a call's
# limit goes on in the next call, when its jobs resume (`ablate --resume`, `time_to_quality --run-dir`).
# A line per job as it ends. What comes back (a call returns at most 8 files): the .tgz files the jobs
# wrote, moved up into $OUT; every job's log and folder in $OUT/job_logs.tgz; and the paths of $PACK
# (e.g. PACK="runs/ablate_x runs/ttq_out") in $OUT/records.tgz, without checkpoints and images.
# A GPU named twice in GPUS runs two jobs at a time (runs timed by steps, not by seconds).
# $RESUME_PACK=1: also $PACK with its checkpoints, and $DONE, in $OUT/resume.tgz; unpacked here over
# the tree (tar xzf) and `runs` carried, the next call resumes the queue on a fresh machine.
source tools/gpu_env.sh >/dev/null
OUT=${OUT:-/tmp/gpu_jobs}; mkdir -p "$OUT/jobs"
DONE=${DONE:-runs/gpu_jobs.done}; mkdir -p "$(dirname "$DONE")"; touch "$DONE"
end=$(( SECONDS + ${DEADLINE:-560} ))
IFS=, read -ra free <<<"${GPUS:-0}"
declare -A gpu_of line_of
mapfile -t lines <"$1"

reap() {  # wait for one job to end, give its GPU back and record it
  local pid rc
  wait -n -p pid; rc=$?
  free+=("${gpu_of[$pid]}")
  local k=${line_of[$pid]}
  [ "$rc" -eq 0 ] && printf '%s\n' "${lines[k]}" >>"$DONE"
  echo "[$(( SECONDS ))s] line $((k + 1)) rc=$rc GPU ${gpu_of[$pid]}: $(tail -n 1 "$OUT/jobs/$((k + 1)).log")"
  unset "gpu_of[$pid]" "line_of[$pid]"
}

for k in "${!lines[@]}"; do
  job=${lines[k]}
  [[ $job =~ ^[[:space:]]*(#|$) ]] && continue
  grep -qxF -- "$job" "$DONE" && { echo "line $((k + 1)): done in an earlier call"; continue; }
  while [ ${#free[@]} -eq 0 ]; do reap; done
  left=$(( end - SECONDS ))
  [ "$left" -gt 30 ] || { echo "line $((k + 1)) and later: not started, deadline"; break; }
  gpu=${free[0]}; free=("${free[@]:1}")
  export JOB_OUT=$OUT/jobs/$((k + 1)); mkdir -p "$JOB_OUT"
  CUDA_VISIBLE_DEVICES=$gpu timeout "$left" bash -c "$job" >"$OUT/jobs/$((k + 1)).log" 2>&1 &
  gpu_of[$!]=$gpu; line_of[$!]=$k
  echo "[$(( SECONDS ))s] line $((k + 1)) on GPU $gpu: $job"
done
while [ ${#gpu_of[@]} -gt 0 ]; do reap; done

for f in "$OUT"/jobs/*/*.tgz; do [ -f "$f" ] && mv "$f" "$OUT/$(basename "$(dirname "$f")")_$(basename "$f")"; done
tar czf "$OUT/job_logs.tgz" -C "$OUT" jobs && rm -rf "$OUT/jobs"
renders=(--exclude='images' --exclude='depth' --exclude='*.partial')  # never returned
# shellcheck disable=SC2086
[ -z "$PACK" ] || tar czf "$OUT/records.tgz" --exclude='*.pt' "${renders[@]}" $PACK "$DONE"
# shellcheck disable=SC2086
[ -z "$PACK" ] || [ -z "$RESUME_PACK" ] || tar czf "$OUT/resume.tgz" "${renders[@]}" $PACK "$DONE"
