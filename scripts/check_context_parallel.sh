#!/usr/bin/env bash
# run.context_parallel on N GPUs against one GPU (see scripts/check_context_parallel.py):
#   scripts/check_context_parallel.sh [MODEL] [N] [OUT] [key=value ...]
# defaults: cogvideox-5b, 2 GPUs, /tmp/geco-context-parallel. Prints each run's time and peak memory
# per rank, the differences of the split run from the one-GPU run, and PASS or FAIL.
set -euo pipefail
model="${1:-cogvideox-5b}"
processes="${2:-2}"
out="${3:-/tmp/geco-context-parallel}"
shift $(( $# < 3 ? $# : 3 ))
cd "$(dirname "$0")/.."
python scripts/check_context_parallel.py --model "$model" --out "$out" "$@"
torchrun --nproc-per-node "$processes" scripts/check_context_parallel.py --model "$model" --out "$out" "$@"
