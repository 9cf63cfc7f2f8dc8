#!/usr/bin/env bash
# From a nuScenes dataroot to a bundle meant for scenes it never saw, in one command (issue 47):
#
#   bash scripts/train_real.sh DATAROOT OUT [--steps N] [--max-scenes N] [--town-scenes N] [--town-frames N]
#
# time split -> synthetic town -> pseudo-labels -> training from both at once -> length chosen on the val
# block -> export to OUT/bundle. Each stage prints its time and reuses what an interrupted run left
# (ago_train/train_real.py; docs/training.md, "Training on your own data"). Needs the training extra.
# Score the held-out test keyframes: python -m benchmarks.train_real --run OUT
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}"   # the checkout this script is in
if [ $# -lt 2 ]; then echo "usage: bash scripts/train_real.sh DATAROOT OUT [options of ago train-real]" >&2; exit 2; fi
exec python -m ago_runtime train-real "$@"
