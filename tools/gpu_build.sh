#!/usr/bin/env bash
# Build our kernels and nerfacc's side by side on the GPU machine and pack both builds into
# $OUT/gpu_cache.tgz (unpack it here into .gpu_cache and carry that: later calls skip the builds).
source tools/gpu_env.sh >/dev/null
OUT=${OUT:-/tmp/gpu_build}; mkdir -p "$OUT" "$TORCH_EXTENSIONS_DIR"
t0=$SECONDS
build() {  # build LOG LABEL: our kernels from the current folder, on $PYTHONPATH
  timeout 420 python -c "from mixer_nerf import _extension as e; assert e.has_cuda_kernels()" >"$OUT/$1.log" 2>&1
  echo "$2 build rc=$? $((SECONDS - t0))s"
}
# $SKIP_NERFACC: the call needs no nerfacc (its JIT build took 65-83 s even with .gpu_cache carried).
[ -n "$SKIP_NERFACC" ] || (timeout 400 python -c "from nerfacc.cuda import _backend" >"$OUT/nerfacc_build.log" 2>&1
  echo "nerfacc build rc=$? $((SECONDS - t0))s") &
# .baseline/csrc (e.g. `git archive REV csrc | tar -x -C .baseline`): the kernels to compare
# against, built beside ours in a copy of the tree (tools/gpu_check.sh bench_base runs there).
# Where the ops' schemas changed, archive REV's mixer_nerf too: what .baseline holds replaces the copy's.
if [ -d .baseline/csrc ]; then
  rm -rf "$BASELINE_TREE" && mkdir -p "$BASELINE_TREE" && cp -r mixer_nerf benchmarks tools "$BASELINE_TREE"/ \
    && cp -r .baseline/. "$BASELINE_TREE"/
  (cd "$BASELINE_TREE" && PYTHONPATH=$BASELINE_PYTHONPATH build baseline_build baseline) &
fi
build build mixer_nerf
wait
(cd "$MIXER_NERF_CACHE" && tar czf "$OUT/gpu_cache.tgz" $(find build -name mixer_nerf_C.so) torch_extensions)
