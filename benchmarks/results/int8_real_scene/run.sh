#!/usr/bin/env bash
# int8 (post-training, with --int8-float) against fp32 on the real nuScenes scene: label agreement only (the shipped
# model is synthetic-trained; no GT here). As run on 2026-12-07 (results: ../int8_real_scene.md).
set -euo pipefail
cd "$(dirname "$0")/../../.."
W=${W:-/tmp/s23}
SCENE=../shared/data/nuscenes-scene
ago export models/default/checkpoint.pt -o $W/b_int8 --int8 --int8-float backbone.stem --int8-float backbone.stage8 \
    --readout-grid 200x200x16 --train-bank-only
ago export models/default/checkpoint.pt -o $W/b_int8_real --int8 --int8-float backbone.stem --int8-float backbone.stage8 \
    --readout-grid 200x200x16 --train-bank-only --calibration-data $SCENE
ago export models/default/checkpoint.pt -o $W/b_int8_16 --int8 --int8-float backbone.stem --int8-float backbone.stage8 \
    --int8-float backbone.stage16 --readout-grid 200x200x16 --train-bank-only
ago infer --images $SCENE --bundle $W/b_int8 --out $W/real_fp32 --picture none
ago infer --images $SCENE --bundle $W/b_int8 --out $W/real_int8 --picture none --int8
ago infer --images $SCENE --bundle $W/b_int8_real --out $W/real_int8r --picture none --int8
ago infer --images $SCENE --bundle $W/b_int8_16 --out $W/real_int8_16 --picture none --int8
W=$W python - <<'PY'
import os
import numpy as np
from ago_runtime.formats.nuscenes import NuScenesDataset
W = os.environ["W"]
ds = NuScenesDataset("../shared/data/nuscenes-scene", load_images=False, load_extras=False)
splits = {"all 41": range(len(ds)), "val (last 11)": ds.split("val"), "train (first 30)": ds.split("train")}
def agree(b, idx):
    same = n = oc = on = 0
    for i in idx:
        name = ds[i].token
        fa, fb = np.load(f"{W}/real_fp32/{name}.npz"), np.load(f"{W}/{b}/{name}.npz")
        a, q, free = fa["semantics"], fb["semantics"], int(fa["free_index"])
        same += (a == q).sum(); n += a.size
        occ = (a != free) | (q != free); oc += ((a == q) & occ).sum(); on += occ.sum()
    return 100 * same / n, 100 * oc / on
for b in ("real_int8", "real_int8r", "real_int8_16"):
    for s, idx in splits.items():
        print(b, s, "all %.3f %%, occupied by either %.3f %%" % agree(b, list(idx)))
PY
