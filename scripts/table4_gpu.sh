#!/usr/bin/env bash
# Flickering Atari on a GPU: checks --device cuda end to end for the three agents, times them on
# Flickering Pong, and prints frames/s and the hours the paper's Table 4 would take at those rates.
# About 5 minutes on one GPU. Needs this package with its atari and minatar extras installed
# (make setup, or pip install -e '.[atari,minatar]') and torch with CUDA.
#   bash scripts/table4_gpu.sh [OUTPUT_DIR] [FRAMES]
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-outputs/gpu_table4}
frames=${2:-16000}
bin=escort-rl
[ -x .venv/bin/escort-rl ] && bin=.venv/bin/escort-rl
py=python3
[ -x .venv/bin/python ] && py=.venv/bin/python

$py -c 'import torch, sys; ok = torch.cuda.is_available(); print("torch", torch.__version__, "cuda:", ok,
torch.cuda.get_device_name(0) if ok else ""); sys.exit(0 if ok else "no CUDA device: this check needs a GPU")'

# 1. End to end on cuda: each agent trains on Flickering Pong (and a MinAtar game) for a few thousand
#    frames; the report gives each one's training frames/s, envs included, and the hours of one seed
#    of the paper's 50M frames.
$bin bench atari --games pong breakout --agents gru dvrl escort_latent --frames "$frames" --device cuda \
  --threads 4 --output "$out/atari"

# 2. The networks alone on cuda, ESCORT-latent's speed choices one by one, and Table 4's projected hours
#    (50M frames x 4 games x 3 seeds per agent).
$bin bench atari-cost --games pong breakout --device cuda --repeats 10 --output "$out/cost"
