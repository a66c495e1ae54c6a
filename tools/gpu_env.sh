# Source on the GPU machine: nerfacc 0.5.3 from the carried wheel, sm_90 builds, unbuffered output,
# the JIT cache in the carried .gpu_cache (a build from an earlier call is reused).
set -o pipefail
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16
export MIXER_NERF_CACHE=${MIXER_NERF_CACHE:-$PWD/.gpu_cache}
if compgen -G ".whl/*.whl" >/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD
fi
export PYTHONPATH=${PYTHONPATH:-$PWD}
nvidia-smi --query-gpu=name,memory.total,clocks.sm --format=csv,noheader
