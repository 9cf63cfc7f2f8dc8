#!/usr/bin/env bash
# A cpu-preset model on the Occ3D grid (200 x 200 x 16, TPV planes 100 x 100), trained briefly on a small
# synthetic town, for the 200x200x16 rows of benchmarks/runtime_speed.py (--ckpt-200): its speed depends on
# how many voxels the model calls occupied (the runtime runs the adapted branch on those only), which a
# random-weights model gets wrong (~100 %). Not a model to use: 600 steps, 6 scenes. About 25 min here
# (synth 3 min, pseudo-labels 3 min, training 19 min). Usage:
#   bash benchmarks/make_model_200.sh [WORK_DIR]      # -> WORK_DIR/train200/last.pt
set -euo pipefail
WORK="${1:-work/s6}"
AGO="python -m ago_runtime"
GRID='{"range_min": [-40.0, -40.0, -1.0], "range_max": [40.0, 40.0, 5.4], "voxel_size": [0.4, 0.4, 0.4], "shape": [200, 200, 16]}'
[ -f "$WORK/synth/splits.json" ] || $AGO synth --out "$WORK/synth" --scenes 6 --frames 16 --seed 7 \
    --image-size 704x396 --grid 200x200x16 --jobs 2
$AGO pseudo-labels --data "$WORK/synth" --out "$WORK/pseudo200" --prompts cw --grid 200x200x16 --split train \
    --segmenter sim --embedder sim --keyframes 10 --interval 1
RESUME=""
[ -f "$WORK/train200/last.pt" ] && RESUME="--resume"
$AGO train --config cpu --data "$WORK/synth" --pseudo "$WORK/pseudo200" --prompts cw --out "$WORK/train200" \
    --set "model.grid=$GRID" --set model.tpv_h=100 --set model.tpv_w=100 --set max_steps=600 --set ckpt_every=100 $RESUME
echo "$WORK/train200/last.pt"
