"""Learning curve of a training run: val mIoU, geometry IoU and occupancy ratio at several step counts.

    python -m benchmarks.learning_curve --run RUN_DIR --data DATASET [--fresh FRESH_DATASET] \
        [--pseudo PSEUDO_DIR] [--out benchmarks/results/learning_curve.md] [--figure docs/figures/learning_curve.png]

RUN_DIR is an `ago train` output folder whose config has `snapshot_steps` (model-only checkpoints in
RUN_DIR/snapshots/step_NNNNNN.pt, plus last.pt). Every snapshot is scored with `ago eval`'s code
(ago_train.evaluate.evaluate, Occ3D metric over mask_camera at the GT resolution) on
- the val split of DATASET (scenes of the training town's seed the run never trained on), and
- FRESH_DATASET, split "all": a town generated with a seed never used in training (`ago synth --seed S`).
Per snapshot: mIoU, geometry IoU, and the occupancy ratio = predicted occupied / GT occupied voxels
inside the camera mask (1 = right amount of matter; a scene prior that fills the grid gives >> 1).
With --pseudo, the pseudo-labels of the same val frames are scored too (the ceiling the model learns
from; unknown voxels count as free). Scores are cached in RUN_DIR/curve/, so a rerun only scores new
snapshots. Writes a markdown table (with the command) and a PNG plot.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from ago_runtime.atomic import atomic_path, write_json, write_text  # noqa: E402
from ago_runtime.pictures.charts import PALETTE, line_chart  # noqa: E402


def occupancy_ratio(metric_summary: dict) -> float:
    """Predicted occupied / GT occupied voxels (camera mask) from the metric's confusion matrix."""
    conf = np.asarray(metric_summary["confusion"], dtype=np.float64)   # rows GT, cols prediction
    free = int(metric_summary["free_index"])
    keep = [i for i in range(conf.shape[0]) if i != free]
    gt_occ = conf[keep, :].sum()
    pred_occ = conf[:, keep].sum()
    return float(pred_occ / max(gt_occ, 1.0))


def score(ckpt: Path, data: str, split: str, cache: Path) -> dict:
    if cache.is_file():
        return json.loads(cache.read_text())
    from ago_train.evaluate import evaluate

    r = evaluate(ckpt, data, split=split, quiet=True, device="cpu")
    s = r["metric"]
    out = {"mIoU": r["mIoU"], "geometry_IoU": r["geometry_IoU"], "occupancy_ratio": occupancy_ratio(s),
           "per_class": dict(s["iou"]),
           "frames": r["frames"]}
    write_json(cache, out)
    return out


def pseudo_ceiling(pseudo: str, data: str, split: str) -> dict:
    """The pseudo-labels of `split`'s frames scored against GT like a prediction (unknown -> free)."""
    from ago_runtime.scoring.metric import OccupancyMetric, upsample_nearest
    from ago_runtime.formats.datasets import open_dataset
    from ago_train.dataset import PseudoLabelSet

    p = PseudoLabelSet.open(pseudo)
    ls = p.label_space()
    K = ls.num_classes
    lut = ls.gt_lut(free_index=K).astype(np.uint8)
    ds = open_dataset(data, load_images=False, load_extras=False)
    m = OccupancyMetric(list(ls.class_names) + ["free"], free_index=K)
    n = 0
    for i in ds.split(split):
        scene, token = ds.scene_of(i), ds.sample_tokens[i]
        if not p.has(scene, token):
            continue
        sem = p.labels(scene, token)
        pred = np.where((sem == 255) | (sem == 17), K, sem).astype(np.uint8)
        gt = ds[i].gt
        factor = tuple(g // s for g, s in zip(gt.semantics.shape, pred.shape))
        m.update(upsample_nearest(pred, factor), lut[gt.semantics], gt.mask_camera.astype(bool))
        n += 1
    if n == 0:
        return {}
    s = m.summary()
    return {"mIoU": s["mIoU"], "geometry_IoU": s["geometry_IoU"], "occupancy_ratio": occupancy_ratio(s), "frames": n,
            "per_class": dict(s["iou"])}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--fresh", default=None)
    ap.add_argument("--pseudo", default=None)
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/learning_curve.md"))
    ap.add_argument("--figure", default=str(REPO / "docs/figures/learning_curve.png"))
    args = ap.parse_args(argv)
    run = Path(args.run)
    snaps = sorted((run / "snapshots").glob("step_*.pt"))
    if not snaps:
        raise SystemExit(f"error: {run}/snapshots: no snapshots (train with --set 'snapshot_steps=[...]')")
    from ago_runtime.progress import track

    rows = []
    for ckpt in track(snaps, "scoring snapshots", total=len(snaps)):
        step = int(ckpt.stem.split("_")[1])
        row = {"step": step, "val": score(ckpt, args.data, args.split, run / "curve" / f"{ckpt.stem}_val.json")}
        if args.fresh:
            row["fresh"] = score(ckpt, args.fresh, "all", run / "curve" / f"{ckpt.stem}_fresh.json")
        rows.append(row)
    ceiling = pseudo_ceiling(args.pseudo, args.data, args.split) if args.pseudo else {}
    # training loss at each snapshot (mean of the logged lines up to it)
    log = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines()] if (run / "log.jsonl").is_file() else []

    def loss_at(step):
        near = [r["total"] for r in log if step - 50 < r["step"] <= step]
        return float(np.mean(near)) if near else float("nan")

    cfg = json.loads((run / "config.json").read_text())
    cmd = "python -m benchmarks.learning_curve " + " ".join(argv if argv is not None else sys.argv[1:])
    head = ["step", "train loss", f"{args.split} mIoU", f"{args.split} geometry IoU", f"{args.split} occupancy ratio"]
    if args.fresh:
        head += ["fresh-town mIoU", "fresh-town geometry IoU", "fresh-town occupancy ratio"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---:|" * len(head)]
    for r in rows:
        cells = [str(r["step"]), f"{loss_at(r['step']):.3f}", f"{r['val']['mIoU']:.2f}",
                 f"{r['val']['geometry_IoU']:.2f}", f"{r['val']['occupancy_ratio']:.2f}"]
        if args.fresh:
            cells += [f"{r['fresh']['mIoU']:.2f}", f"{r['fresh']['geometry_IoU']:.2f}",
                      f"{r['fresh']['occupancy_ratio']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    if ceiling:
        lines.append(f"| pseudo-labels ({ceiling['frames']} {args.split} frames) | | {ceiling['mIoU']:.2f} | "
                     f"{ceiling['geometry_IoU']:.2f} | {ceiling['occupancy_ratio']:.2f} |" + (" | | |" if args.fresh else ""))
    last = rows[-1]
    # object classes of the run's label space (Occ3D-nuScenes' or Occ3D-Waymo's names)
    classes = [c for c in ("car", "bus", "truck", "vehicle", "pedestrian", "bicyclist", "barrier", "sign")
               if c in last["val"]["per_class"]]
    per = [f"{c} {last['val']['per_class'].get(c)}" for c in classes]
    per_f = [f"{c} {last['fresh']['per_class'].get(c)}" for c in classes] if args.fresh else []
    text = f"""# Learning curve: `{run}`

Command: `{cmd}`

Run: preset `{cfg.get('name')}`, {cfg.get('train_voxels')} sampled voxels per step ({cfg.get('voxel_sampling', 'priority')}),
frozen backbone stages {cfg['model'].get('frozen_stages')}, lr {cfg.get('lr')}, data `{cfg.get('data')}`, pseudo-labels `{cfg.get('pseudo')}`.
Scores: Occ3D metric over the GT camera mask at the GT resolution (200x200x16; the model's {'x'.join(map(str, cfg['model']['grid']['shape']))} is
repeated up to it, `ago eval --readout model`); occupancy ratio = predicted occupied / GT occupied voxels in the camera mask.

{chr(10).join(lines)}

Object classes at the last snapshot (IoU %): {args.split}: {', '.join(per)}{'; fresh town: ' + ', '.join(per_f) if per_f else ''}.

![learning curve]({os.path.relpath(args.figure, Path(args.out).parent)})
"""
    write_text(args.out, text)
    steps = [r["step"] for r in rows]
    series = [(f"{args.split} mIoU", steps, [r["val"]["mIoU"] for r in rows], PALETTE[0]),
              (f"{args.split} geometry IoU", steps, [r["val"]["geometry_IoU"] for r in rows], PALETTE[1])]
    if args.fresh:
        series += [("fresh mIoU", steps, [r["fresh"]["mIoU"] for r in rows], PALETTE[2]),
                   ("fresh geometry IoU", steps, [r["fresh"]["geometry_IoU"] for r in rows], PALETTE[3])]
    img = line_chart(f"learning curve: {run.name}", series, x_label="optimiser steps", y_label="%",
                     log_x=True)
    import cv2

    with atomic_path(args.figure) as tmp:
        cv2.imwrite(str(tmp), img)
    print(text)
    return {"rows": rows, "ceiling": ceiling}


if __name__ == "__main__":
    main()
