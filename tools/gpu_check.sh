#!/usr/bin/env bash
# GPU checks in one device call: JIT-build the kernels, then the named stages in order.
# Usage on the GPU machine: bash tools/gpu_check.sh [STAGE ...]   (default: every stage)
#   pytest[:PATH] the whole test suite, or one test file ($PYTEST_WORKERS: pytest-xdist workers, each
#                 with $PYTEST_THREADS (2) CPU threads, spread over $MIXER_NERF_TEST_GPUS GPUs; $PYTEST_LIMIT:
#                 seconds, default 360)
#   memcheck      compute-sanitizer memcheck over the CUDA tests of every op ($MEMCHECK_TESTS: some)
#   racecheck     compute-sanitizer racecheck over those of the kernels with shared memory
#                 ($RACECHECK_TESTS: some)
#                 (both in the background, side by side with later stages: name them last)
#   error_budget  python -m benchmarks.error_budget --device cuda
#   bench[:OPS]   python -m benchmarks.bench_ops --device cuda [--ops OPS] ($BENCH_LIMIT: seconds, default 420)
#   bench_base[:OPS] the same over the kernels of .baseline/csrc (see tools/gpu_build.sh), into
#                 results/ops_baseline: an A/B of a kernel change on one card in one call
#   long_run      python -m benchmarks.long_run_stability (--budget $LONG_RUN_BUDGET, default 400 s)
#   ncu[_packed|_hierarchical] Nsight Compute (--set full) of the composite forward and backward kernels
#                 (_packed: composite_packed's, on bench_ops' packed case; _hierarchical: hierarchical_samples'
#                 default call), tools/profile_op.py
#   ncu_base[...] the same over the kernels of .baseline/csrc, its log only: the A/B of a kernel change
#   field         python -m benchmarks.bench_field $FIELD_ARGS (the MLP's cost per preset and precision)
#   crash         tools/diagnose_exception_crash.py (in the background, alongside later stages)
#   checks        tools/profile_checks.py (what the default value checks cost a composite step, and where)
#   neighbours    tools/profile_neighbours.py (a composite step's time alone and with a peer's step between)
#   host          python -m benchmarks.host_overhead --device cuda (host time a call of each differentiable op)
#   train_step    tools/profile_train_step.py for presets A and D on .data/lego_400 ($STEP_PRESETS), one
#                 after the other: ms per step, GPU busy, kernels, host waits
# Logs and results are packed into $OUT/gpu_check.tgz (the device returns at most 8 files); its
# results/ folder is laid out as benchmarks/results/ (<benchmark>/<device>.*), to be copied over it.
# The builds go into $OUT/gpu_cache.tgz by tools/gpu_build.sh (unpack it into .gpu_cache and carry
# that to skip the builds next time); a summary is printed last.
source tools/gpu_env.sh >/dev/null
OUT=${OUT:-/tmp/gpu_check}; LOGS=$OUT/gpu_check_logs; mkdir -p "$OUT/results" "$LOGS"
summary=$(mktemp)
# $DEADLINE (seconds since the start, default 570) caps every step, so that the results are packed
# before the device call's own limit.
step() {  # step NAME SECONDS CMD...: run with a time limit, keep the log, record the exit status
  local name=$1 limit=$2; shift 2
  local t0=$SECONDS left=$((${DEADLINE:-570} - SECONDS))
  [ "$left" -lt "$limit" ] && limit=$((left > 1 ? left : 1))
  timeout "$limit" "$@" >"$LOGS/$name.log" 2>&1
  local rc=$?
  echo "$name rc=$rc $((SECONDS - t0))s: $(grep -E 'passed|failed|ERROR SUMMARY|error' "$LOGS/$name.log" | tail -1)" >>"$summary"
}
# $SKIP_BUILD: built already by this call (tools/gpu_build.sh), e.g. before two runs on two GPUs.
[ -n "$SKIP_BUILD" ] || bash tools/gpu_build.sh >>"$summary"
mv "$OUT/build.log" "$OUT/nerfacc_build.log" "$OUT/baseline_build.log" "$LOGS/" 2>/dev/null
stages=("$@")
# Nsight Compute of two of a case's kernel launches after four (tools/profile_op.py): ncu_stage NAME LAYOUT
ncu_case() { case $1 in _packed) echo composite_packed ;; _hierarchical) echo hierarchical_samples ;; *) echo composite ;; esac; }
ncu_stage() {
  local case; case=$(ncu_case "$2")
  step "$1" 240 ncu --set full --import-source no --kernel-name "regex:$(python tools/profile_op.py --kernel "$case")" \
    --launch-skip 4 --launch-count 2 python tools/profile_op.py "$case"
}
[ ${#stages[@]} -eq 0 ] && stages=(crash pytest error_budget bench memcheck racecheck)
for stage in "${stages[@]}"; do
  case $stage in
    # Each xdist worker would otherwise start as many CPU threads as the machine has cores.
    # -v names each finished test, so a run cut by its limit says which tests never finished
    # (and a process list taken 20 s before the limit says what they were doing). One log per stage.
    pytest*) paths=${stage#pytest}; log=pytest${paths:+_$(basename "${paths#:}" .py)}
      limit=$(( ${PYTEST_LIMIT:-360} < ${DEADLINE:-570} - SECONDS ? ${PYTEST_LIMIT:-360} : ${DEADLINE:-570} - SECONDS ))
      # Detached from stdout: a caller's pipe (`gpu_check.sh | tail`) would otherwise stay open, and
      # wait, until the watcher's sleep ended (~300 s lost in one call).
      ( sleep $((limit - 20)); ps -eo pid,ppid,etime,pcpu,rss,args --sort=-pcpu | cut -c1-300 | head -60 \
          >"$LOGS/${log}_ps.txt" ) </dev/null >/dev/null 2>&1 & watcher=$!
      ( [ -n "$PYTEST_WORKERS" ] && export OMP_NUM_THREADS=${PYTEST_THREADS:-2}
        step "$log" "$limit" python -m pytest -v -p no:cacheprovider -rs --durations=25 \
          ${PYTEST_WORKERS:+-n $PYTEST_WORKERS} ${paths#:} )
      pkill -P $watcher 2>/dev/null; kill $watcher 2>/dev/null
      python -m pytest --collect-only -q -p no:cacheprovider ${paths#:} 2>/dev/null | grep '::' | LC_ALL=C sort >"$LOGS/${log}_collected.txt"
      # A test id runs to the end of its line (parameter ids may hold spaces); xdist puts it after the outcome.
      outcome='(PASSED|FAILED|SKIPPED|ERROR|XFAIL|XPASS)'
      sed -nE -e "s/^\[gw[0-9]+\] \[ *[0-9]+%\] $outcome (tests\/.*[^ ]) *\$/\2/p" \
        -e "s/^(tests\/.*::.*[^ ]) $outcome +\[ *[0-9]+%\]\$/\1/p" "$LOGS/$log.log" | LC_ALL=C sort -u >"$LOGS/${log}_finished.txt"
      comm -23 "$LOGS/${log}_collected.txt" "$LOGS/${log}_finished.txt" >"$LOGS/${log}_unfinished.txt"
      echo "$log: $(wc -l <"$LOGS/${log}_finished.txt") of $(wc -l <"$LOGS/${log}_collected.txt") finished; unfinished: $(head -c 3000 "$LOGS/${log}_unfinished.txt" | tr '\n' ' ')" >>"$summary" ;;
    # memcheck: every op's CUDA tests. racecheck (shared-memory hazards, ~10x slower): the
    # kernels with shared memory, without the largest cases (more blocks, no new hazards).
    memcheck) step memcheck 420 compute-sanitizer --tool memcheck --error-exitcode 1 python -m pytest -q \
      -p no:cacheprovider ${MEMCHECK_TESTS:-tests/test_sample_pdf.py tests/test_composite.py \
      tests/test_positional_encoding.py tests/test_ray_marching.py tests/test_segment_ops.py tests/test_mlca.py} \
      -m "cuda and not profiler" -k "not opcheck and not 32_bit" & ;;
    racecheck) step racecheck 420 compute-sanitizer --tool racecheck --error-exitcode 1 python -m pytest -q \
      -p no:cacheprovider ${RACECHECK_TESTS:-tests/test_sample_pdf.py tests/test_positional_encoding.py \
      tests/test_segment_ops.py tests/test_mlca.py} -m "cuda and not profiler" \
      -k "not opcheck and not 65536 and not 100003 and not 32_bit and not training_sized" & ;;
    error_budget) step error_budget 150 python -m benchmarks.error_budget --device cuda \
      --out "$OUT/results/error_budget" ;;
    # bench_base before bench: the pattern bench* would take it.
    bench_base*) ops=${stage#bench_base}; [ -d "$BASELINE_TREE/csrc" ] || { echo "bench_base: no .baseline/csrc" >>"$summary"; continue; }
      ( cd "$BASELINE_TREE" && export PYTHONPATH=$BASELINE_PYTHONPATH && step bench_base 420 python -m benchmarks.bench_ops \
        --device cuda --repeats 30 --out "$OUT/results/ops_baseline" ${ops:+--ops ${ops#:}} ) ;;
    bench*) ops=${stage#bench}; step bench_ops "${BENCH_LIMIT:-420}" python -m benchmarks.bench_ops --device cuda --repeats 30 \
      --out "$OUT/results/ops" ${ops:+--ops ${ops#:}} ;;
    long_run) step long_run 560 python -m benchmarks.long_run_stability \
      --out "$OUT/results/long_run_stability" --budget "${LONG_RUN_BUDGET:-400}" ;;
    # ncu_base before ncu: the pattern ncu* would take it.
    ncu_base*) layout=${stage#ncu_base}; [ -d "$BASELINE_TREE/csrc" ] || { echo "$stage: no .baseline/csrc" >>"$summary"; continue; }
      ( cd "$BASELINE_TREE" && export PYTHONPATH=$BASELINE_PYTHONPATH && ncu_stage "$stage" "$layout" ) ;;
    ncu*) layout=${stage#ncu}; ncu_stage "$stage" "$layout"
      tag=$(python -c "from benchmarks.harness import device_tag; print(device_tag('cuda'))")
      mkdir -p "$OUT/results/ops" && cp "$LOGS/$stage.log" "$OUT/results/ops/${tag}_$(ncu_case "$layout")_ncu.txt" ;;
    field) step field 400 python -m benchmarks.bench_field --out "$OUT/results/train_step" $FIELD_ARGS ;;
    checks) step checks 120 python tools/profile_checks.py ;;
    neighbours) step neighbours 180 python tools/profile_neighbours.py ;;
    host) step host 120 python -m benchmarks.host_overhead --device cuda --out "$OUT/results/ops" ;;
    train_step) for preset in ${STEP_PRESETS:-A D}; do
        step "train_step_$preset" 150 python tools/profile_train_step.py --preset "$preset" --warmup 1000 \
          --out "$OUT/results/train_step"
        head -n 1 "$LOGS/train_step_$preset.log"; done ;;
    crash) timeout 400 python tools/diagnose_exception_crash.py >"$LOGS/crash.log" 2>&1 & ;;
    *) echo "unknown stage $stage"; exit 2 ;;
  esac
done
wait
tail -n 40 "$LOGS/bench_ops.log" 2>/dev/null
tail -n 40 "$LOGS/bench_base.log" 2>/dev/null
tail -n 45 "$LOGS/field.log" 2>/dev/null
tail -n 16 "$LOGS/long_run.log" 2>/dev/null
cat "$LOGS/crash.log" 2>/dev/null
tail -n 30 "$LOGS/checks.log" 2>/dev/null
# Only this script's logs: a caller's own files in $OUT stay where they are.
(cd "$OUT" && tar czf gpu_check.tgz results -C "$LOGS" . && rm -r results "$LOGS")
cat "$summary"
