#!/usr/bin/env bash
# ESCORT's speed on a GPU: the rows of docs/results/notes/escort_speed.md, measured on cuda.
# About 5 minutes on one GPU; needs this package (make setup) and torch with CUDA.
#   bash scripts/escort_speed_gpu.sh [OUTPUT_DIR]
# DEVICE=cpu QUICK=1 runs the same commands as a smoke test on a CPU.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-outputs/gpu_escort_speed}
device=${DEVICE:-cuda}
bin=escort-rl
[ -x .venv/bin/escort-rl ] && bin=.venv/bin/escort-rl
py=python3
[ -x .venv/bin/python ] && py=.venv/bin/python
if [ -n "${QUICK:-}" ]; then
  profile=(--quick); grid=(--dims 10 --particles 20 --batch-sizes 2 --num-steps 3 --repeats 1)
  rollout=(--num-envs 4 --steps 5 --batches 1)
else
  profile=(); grid=(--dims 10 20 --particles 100 1000 --batch-sizes 1 64 --num-steps 50 --repeats 5)
  rollout=(--num-envs 64 --steps 50 --batches 3)
fi

if [ "$device" = cuda ]; then
  $py -c 'import torch, sys; ok = torch.cuda.is_available(); print("torch", torch.__version__, "cuda:", ok,
torch.cuda.get_device_name(0) if ok else ""); sys.exit(0 if ok else "no CUDA device: this check needs a GPU")'
fi

# 1. The escort_train update at B = 64 inside a training rollout: its parts, host syncs, recompiles,
#    and its arithmetic bound at the device's matmul rate.
$bin bench profile "${profile[@]}" device="$device" --output "$out/profile"

# 2. One update against d, N and B, ESCORT, SVGD and SIR, eager and compiled, with the bound.
$bin bench cost filter.compile=true "${grid[@]}" --device "$device" --max-pairs 1e9 --output "$out/cost"

# 3. Rollouts on escort_train and on SIR beliefs, B = 64, with the DeepSets policy.
for f in escort_train sir; do
  $bin bench throughput filter=$f device="$device" --collector-workers 1 "${rollout[@]}" --output "$out/throughput_$f"
done
