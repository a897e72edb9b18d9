#!/usr/bin/env bash
# ON the GPU machine (a `device_sweep.sh commands` line): one trainer-pilot arm on one GPU, one `hpgs bench` sweep
# per seed side by side under that GPU's MPS daemon (scripts/device_gpu_benches.sh), each into OUT/s<seed>/<arm> (a
# results folder keeps one --extra-args, so seeds and arms get folders of their own; merge them afterwards).
#   PILOT="--suite tune6 --protocols fisherrf --step-scale 0.5 --selectors random hpgs --final-set all \
#          --no-references --runs-per-gpu 12" \
#   bash scripts/device_arm_sweeps.sh GPU OUT ARM 'EXTRA ARGS' SEED [SEED ...]
# e.g. bash scripts/device_arm_sweeps.sh 0 /tmp/extra w0.05 '--pipeline.model.depth-loss.weight 0.05' 0 1 2
# DRY=1 prints the sweeps instead of running them.
set -u
gpu=$1 out=$2 arm=$3 extra=$4
shift 4
: "${PILOT:?set PILOT to the hpgs bench arguments every sweep shares}"
sweeps=()
for seed in "$@"; do
  sweeps+=("$PILOT --seeds $seed --out $out/s$seed/$arm --extra-args='$extra'")
done
if [ "${DRY:-0}" = 1 ]; then
  printf '%s\n' "${sweeps[@]}"
  exit 0
fi
exec bash "$(dirname "$0")/device_gpu_benches.sh" "$gpu" "${sweeps[@]}"
