"""Read a coarse-trained model's TPV planes on the GT's finer grid: does it thin the surfaces?

A model of the `cpu` preset predicts on 100 x 100 x 8 voxels (0.8 m); the Occ3D GT is 200 x 200 x 16
(0.4 m), so `ago eval` repeats every predicted voxel 2 x 2 x 2 times and every surface comes out at
least 0.8 m thick (issue "The model must see": the model calls ~1.5x the GT's occupied voxels). The TPV
planes are continuous maps, upsampled bilinearly to the voxel grid anyway (aggregate.py), so the same
planes can be read at the centres of the 0.4 m voxels: nothing is retrained, only the read-out grid
changes (8x the voxels through the decoder MLP).

Scores each checkpoint both ways with `ago_train.evaluate.evaluate` (`ago eval --readout model|gt`) and
prints mIoU, geometry IoU, the predicted / GT occupied ratio and the object classes' IoU:

    python -m benchmarks.fine_query --ckpt work/db24/train_cb05_s1/last.pt --data work/db24/synth --split val
    python -m benchmarks.fine_query --ckpt ... --data work/fresh101 --split all --out benchmarks/results/fine_query.md
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ago_train.evaluate import evaluate

OBJECTS = ("car", "bus", "truck", "pedestrian", "barrier")


def row(ckpt: str, result: dict) -> dict:
    m = result["metric"]
    c, f = np.asarray(m["confusion"]), m["free_index"]
    per_class = {n: m["iou"][n] for n in OBJECTS if n in m["iou"]}     # per-class IoU (%) of the summary
    ratio = (c.sum(0).sum() - c.sum(0)[f]) / max(1, c.sum(1).sum() - c.sum(1)[f])
    return {"ckpt": ckpt, "read-out": result["readout"], "mIoU": result["mIoU"],
            "geometry_IoU": result["geometry_IoU"], "ratio": round(float(ratio), 2), **per_class}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ckpt", action="append", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--out", type=Path, default=None, help="append a markdown table here")
    args = ap.parse_args()
    rows = []
    for ckpt in args.ckpt:
        for readout in ("model", "gt"):
            res = evaluate(ckpt, args.data, split=args.split, max_frames=args.max_frames, device="cpu",
                           readout=readout)
            rows.append(row(ckpt, res))
            print(json.dumps(rows[-1]))
    if args.out:
        cols = list(rows[0])
        lines = [f"\n`python -m benchmarks.fine_query {' '.join('--ckpt ' + c for c in args.ckpt)} --data {args.data} "
                 f"--split {args.split}`\n", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        lines += ["| " + " | ".join(str(r[c]) for c in cols) + " |" for r in rows]
        with open(args.out, "a") as fh:
            fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
