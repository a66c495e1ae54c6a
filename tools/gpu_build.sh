#!/usr/bin/env bash
# Build our kernels and nerfacc's side by side on the GPU machine and pack both builds into
# $OUT/gpu_cache.tgz (unpack it here into .gpu_cache and carry that: later calls skip the builds).
source tools/gpu_env.sh >/dev/null
OUT=${OUT:-/tmp/gpu_build}; mkdir -p "$OUT" "$TORCH_EXTENSIONS_DIR"
t0=$SECONDS
(timeout 400 python -c "from nerfacc.cuda import _backend" >"$OUT/nerfacc_build.log" 2>&1; echo "nerfacc build rc=$? $((SECONDS - t0))s") &
timeout 420 python -c "from mixer_nerf import _extension as e; assert e.has_cuda_kernels()" >"$OUT/build.log" 2>&1
echo "mixer_nerf build rc=$? $((SECONDS - t0))s"
wait
(cd "$MIXER_NERF_CACHE" && tar czf "$OUT/gpu_cache.tgz" $(find build -name mixer_nerf_C.so) torch_extensions)
