"""Query a coarse-trained model's TPV planes on the GT's finer grid: does it thin the surfaces?

A model of the `cpu` preset predicts on 100 x 100 x 8 voxels (0.8 m); the Occ3D GT is 200 x 200 x 16
(0.4 m), so `ago eval` repeats every predicted voxel 2 x 2 x 2 times and every surface comes out at
least 0.8 m thick (issue "The model must see": the model calls ~1.5x the GT's occupied voxels). The TPV
planes are continuous maps that are upsampled bilinearly to the voxel grid anyway (aggregate.py), so
the same planes can be read at the centres of the 0.4 m voxels: nothing is retrained, only the
read-out grid changes (8x the voxels through the decoder MLP).

For each checkpoint, the same frames are scored both ways (torch, one OccupancyMetric each, identifier
`none` as `ago eval` picks for the closed-world bank):
- "coarse": predict on the model grid, nearest-upsample to the GT grid (what `ago eval` does);
- "fine": predict on the GT grid directly, planes read at the 0.4 m voxel centres.

    python benchmarks/fine_query.py --ckpt work/db24/train_cb05/last.pt --data work/db24/synth --split val
    python benchmarks/fine_query.py --ckpt ... --data work/fresh101 --split all --out benchmarks/results/fine_query.md
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from ago_runtime.geometry.preprocess import Preprocess
from ago_runtime.scoring.metric import OccupancyMetric
from ago_train.checkpoint import load_checkpoint
from ago_train.dataset import FrameList, OccSampleDataset, collate
from ago_train.evaluate import _to_gt_resolution, bank_for, checkpoint_label_space, load_model
from ago_train.model.aggregate import planes_to_voxels
from ago_train.model.scoring import class_logits
from ago_train.trainer import open_frames


def predict(model, planes, grid_shape, text, phrase_class, K) -> np.ndarray:
    """(X, Y, Z) uint8 labels (0..K-1 class, K free) of the planes read on `grid_shape`."""
    feats = planes_to_voxels(planes, grid_shape)                 # (1, N, D)
    out = []
    for s in range(0, feats.shape[1], 65536):                     # bounded memory at 200 x 200 x 16
        f = model.decoder_out(model.decoder(feats[:, s:s + 65536]))
        out.append(class_logits(f, text, phrase_class, K, model.free_embedding, None).argmax(-1))
    return torch.cat(out, 1)[0].reshape(grid_shape).numpy().astype(np.uint8)


def occupied_ratio(metric: OccupancyMetric) -> float:
    c = metric.confusion
    f = metric.free_index
    return float((c.sum(0).sum() - c.sum(0)[f]) / max(1, c.sum(1).sum() - c.sum(1)[f]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ckpt", action="append", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--out", type=Path, default=None, help="append a markdown table here")
    args = ap.parse_args()
    torch.set_grad_enabled(False)
    rows = []
    for path in args.ckpt:
        ckpt = load_checkpoint(path, map_location="cpu")
        mcfg, model = load_model(ckpt, torch.device("cpu"), path)
        space = checkpoint_label_space(ckpt)
        K = space.num_classes
        text, phrase_class = bank_for(ckpt, space)
        ds, idx = open_frames(args.data, None, args.split)
        idx = idx[:args.max_frames] if args.max_frames else idx
        grid = mcfg.grid_obj()
        data = OccSampleDataset(FrameList(ds, idx), None, K, grid, Preprocess(mcfg.image_width, mcfg.image_height),
                                gt_lut=space.gt_lut(free_index=K), with_gt=True)
        names = list(space.class_names) + ["free"]
        metrics = {"coarse": OccupancyMetric(names, free_index=K), "fine": OccupancyMetric(names, free_index=K)}
        secs = {"coarse": 0.0, "fine": 0.0}
        loader = torch.utils.data.DataLoader(data, batch_size=1, shuffle=False, collate_fn=collate)
        for i, batch in enumerate(loader):
            planes = model.planes(batch["images"], batch["ego2img"])
            gt, mask = batch["gt"][0], batch["gt_mask"][0]
            gt_np = np.asarray(gt)
            for name, shape in (("coarse", tuple(grid.shape)), ("fine", tuple(gt_np.shape))):
                t = time.perf_counter()
                vol = predict(model, planes, shape, text, phrase_class, K)
                secs[name] += time.perf_counter() - t
                metrics[name].update(_to_gt_resolution(vol, gt_np.shape, "pred"), gt, mask)
            print(f"\r{path}: frame {i + 1}/{len(idx)}", end="", flush=True)
        print()
        for name, m in metrics.items():
            s = m.summary()
            iou = dict(zip(m.semantic_names, (float(x) * 100 for x in m.iou()[:K])))
            rows.append({"ckpt": path, "read-out": name, "mIoU": s["mIoU"], "geometry_IoU": s["geometry_IoU"],
                         "ratio": round(occupied_ratio(m), 2), "voxel stage s/frame": round(secs[name] / len(idx), 3),
                         **{c: round(iou[c], 2) for c in ("car", "bus", "truck", "pedestrian", "barrier")}})
            print(json.dumps(rows[-1]))
    if args.out:
        cols = list(rows[0])
        lines = [f"\n`python benchmarks/fine_query.py {' '.join('--ckpt ' + c for c in args.ckpt)} --data {args.data} "
                 f"--split {args.split}`\n", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        lines += ["| " + " | ".join(str(r[c]) for c in cols) + " |" for r in rows]
        with open(args.out, "a") as f:
            f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
