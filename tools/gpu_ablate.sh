#!/usr/bin/env bash
# On the GPU machine, one device call of a sequential ablation (presets one after another on one GPU),
# resumed across calls:  bash tools/gpu_ablate.sh SCENE NAME PRESETS SEEDS BUDGET  (.data/SCENE, runs/NAME).
# Returns the records without checkpoints, the checkpoints split into files under 15 MiB (a call
# returns files up to 16 MiB: unpack them into runs/ and carry it where the machine went cold), the log.
# DEADLINE (s from the start, default 555) stops the ablation in time to pack; GPUS (e.g. 0,1) spreads
# the runs over those GPUs (ablate --gpus); PRE (a command, e.g. a pytest line) runs after the build,
# its output in pre.log; ABLATE_ARGS (e.g. "--precision bf16") are passed on to ablate. A call that
# carried no .gpu_cache also returns the kernels' build as gpu_cache.tgz.
set -u
t0=$SECONDS
scene=$1 name=$2 presets=$3 seeds=$4 budget=$5
source tools/gpu_env.sh
SKIP_NERFACC=1 OUT=/tmp/build_out bash tools/gpu_build.sh
[ -d .gpu_cache ] || cp /tmp/build_out/gpu_cache.tgz "$OUT"/  # the build, for a later call to carry
echo "build done at $((SECONDS - t0)) s"
if [ -n "${PRE:-}" ]; then
  bash -c "$PRE" >"$OUT/pre.log" 2>&1
  echo "PRE rc=$? at $((SECONDS - t0)) s: $(tail -1 "$OUT/pre.log")"
fi
left=$(( ${DEADLINE:-555} - (SECONDS - t0) ))
timeout -s TERM "$left" python -m mixer_nerf ablate --data ".data/$scene" --presets "$presets" --seeds "$seeds" \
  --time-budget "$budget" --ckpt-every 500 --resume --no-progress ${GPUS:+--gpus "$GPUS"} ${ABLATE_ARGS:-} --out "runs/$name" >"$OUT/ablate.log" 2>&1
echo "ablate rc=$? at $((SECONDS - t0)) s"
tar czf "$OUT/records.tgz" --exclude='*.pt' --exclude='images' runs/"$name"
tar cf - $(find runs/"$name" -name '*.pt') 2>/dev/null | gzip -1 | split -b 15M - "$OUT/pt.tgz.part_"
ls -la "$OUT"; grep -v '^\s*$' "$OUT/ablate.log" | tail -25
