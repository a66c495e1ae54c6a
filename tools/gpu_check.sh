#!/usr/bin/env bash
# One device call: JIT-build the kernels, run the whole test suite on the GPU, compute-sanitizer
# over the CUDA sample_pdf/composite tests, the CUDA error budget and the op benchmarks.
# Usage on the GPU machine: bash tools/gpu_check.sh  (writes under $OUT; prints a summary last)
source tools/gpu_env.sh >/dev/null
export MIXER_NERF_CACHE=${MIXER_NERF_CACHE:-$PWD/.gpu_cache}
OUT=${OUT:-/tmp/gpu_check}; mkdir -p "$OUT/results"
summary=()
step() {  # step NAME SECONDS CMD...: run with a time limit, keep the log, record the exit status
  local name=$1 limit=$2; shift 2
  local t0=$SECONDS
  timeout "$limit" "$@" >"$OUT/$name.log" 2>&1
  local rc=$?
  summary+=("$name rc=$rc $((SECONDS - t0))s: $(grep -E 'passed|failed|ERROR SUMMARY|error' "$OUT/$name.log" | tail -1)")
}
step build 300 python -c "from mixer_nerf import _extension as e; assert e.has_cuda_kernels(); print('CUDA kernels loaded')"
step pytest 240 python -m pytest -q -p no:cacheprovider -rs
step sanitizer 150 compute-sanitizer --tool memcheck --error-exitcode 1 python -m pytest -q -p no:cacheprovider \
  tests/test_sample_pdf.py tests/test_composite.py -m cuda -k "not opcheck"
step error_budget 150 python benchmarks/error_budget.py --device cuda --out "$OUT/results"
step bench_ops 420 python -m benchmarks.bench_ops --device cuda --repeats 30 --out "$OUT/results"
tail -n 40 "$OUT/bench_ops.log"
printf '%s\n' "${summary[@]}"
