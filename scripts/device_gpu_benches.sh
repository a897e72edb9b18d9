#!/usr/bin/env bash
# ON the GPU machine (inside a `device_sweep.sh commands` line, device env set): several `hpgs bench` sweeps that
# share ONE GPU, side by side under one CUDA MPS daemon started here for that GPU (each sweep then finds it through
# $CUDA_MPS_PIPE_DIRECTORY and leaves it running); the daemon quits when the last sweep ends. Use it to run arms
# that differ in --extra-args or --out on the same card (two sweeps starting their own daemons would race for it).
#   bash scripts/device_gpu_benches.sh GPU_INDEX 'BENCH ARGS 1' 'BENCH ARGS 2' ...
# Each ARGS gets `--data-root /tmp/devdata --mps on`; logs go to /tmp/extra/<gpu>-<k>.log.
set -u
gpu=$1; shift
uuid=$(nvidia-smi --query-gpu=uuid --format=csv,noheader -i "$gpu" | tr -d ' ')
control=$(command -v nvidia-cuda-mps-control || echo /usr/local/nvidia/bin/nvidia-cuda-mps-control)
export CUDA_VISIBLE_DEVICES=$uuid CUDA_MPS_PIPE_DIRECTORY=/tmp/mps-$gpu/pipe CUDA_MPS_LOG_DIRECTORY=/tmp/mps-$gpu/log
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
mkdir -p "$CUDA_MPS_PIPE_DIRECTORY" "$CUDA_MPS_LOG_DIRECTORY" /tmp/extra
"$control" -d || { echo "device_gpu_benches: MPS daemon for GPU $gpu did not start" >&2; exit 1; }
trap 'echo quit | "$control"' EXIT
k=0
for args in "$@"; do
  k=$((k + 1))
  # shellcheck disable=SC2086  # ARGS is a list of words
  eval "python3 -m hpgs_ns.cli bench --data-root /tmp/devdata --mps on $args" > "/tmp/extra/gpu$gpu-$k.log" 2>&1 &
done
wait
echo "device_gpu_benches: GPU $gpu done $(date +%s)"
