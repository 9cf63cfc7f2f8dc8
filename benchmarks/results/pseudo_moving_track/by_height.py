"""Occupancy precision / recall of pseudo-labels against Occ3D GT, per z layer, inside the GT camera mask (the
pseudo-labels at 100x100x16 repeated 2x2x1 onto the GT's 200x200x16; unknown pseudo-label voxels count as free).

    python benchmarks/results/pseudo_moving_track/by_height.py NAME=PSEUDO_DIR ... --gts GTS_DIR
"""
import argparse
from pathlib import Path

import numpy as np

from ago_runtime.volumes import upsample_nearest

p = argparse.ArgumentParser()
p.add_argument("runs", nargs="+")
p.add_argument("--gts", required=True)
a = p.parse_args()
res = {}
for run in a.runs:
    name, d = run.split("=", 1)
    tp, fp, fn = np.zeros(16), np.zeros(16), np.zeros(16)
    for f in sorted(Path(d).rglob("labels.npz")):
        g = next(Path(a.gts).rglob(f"{f.parent.name}/labels.npz"))
        with np.load(g) as z:
            gs, cm = z["semantics"], z["mask_camera"].astype(bool)
        with np.load(f) as z:
            po = upsample_nearest(z["semantics"], (2, 2, 1)) < 17
        go = gs != 17
        tp += (po & go & cm).sum(axis=(0, 1))
        fp += (po & ~go & cm).sum(axis=(0, 1))
        fn += (~po & go & cm).sum(axis=(0, 1))
    res[name] = (tp, fp, fn)
print("| z layer | " + " | ".join(f"{n}: precision / recall / false positives" for n in res) + " |")
print("|---:|" + "---:|" * len(res))
for z in range(2, 10):
    print(f"| {z} | " + " | ".join(f"{100 * tp[z] / (tp[z] + fp[z]):.1f} / {100 * tp[z] / (tp[z] + fn[z]):.1f} / "
                                   f"{int(fp[z])}" for tp, fp, fn in res.values()) + " |")
