"""A bundle on synthetic towns it never saw, beside predictors that look at no image.

    python -m benchmarks.default_bundle_towns --towns T101 T202 T303 T404 --prior-data TRAIN_TOWN \
        [--bundle DIR] [--out benchmarks/results/default_bundle_towns.md]

Each town (made by `ago synth` with a seed no training used, fixed before any run) is run through the torch-free
runtime as a user would (`ago infer --images TOWN --picture none`, then `ago metric --gt TOWN/gts`), and scored
beside three predictors that never look at an image, on the same GT frames and camera masks with the same
metric (ago_runtime.scoring.metric.OccupancyMetric):

- all free: every voxel free;
- ground slab: every voxel whose centre is below z = 0.2 m (ego frame) driveable surface, the rest free;
- scene prior: each voxel's most frequent GT label over the TRAINING town's train split
  (ago_runtime.scoring.lidar_agreement.TrainingPrior), i.e. the average street the model was trained in.

If one of them comes close to the bundle, the metric or the model is wrong. Geometry is also broken down by
height (one row per z layer of the GT grid: the share of the visible occupied GT voxels in it, and the bundle's
precision and recall of occupancy there), which says where the wrong occupied voxels lie. The results file records
the command, the bundle's checkpoint sha256 and training settings (its card), the towns, the CPU and the commit.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SLAB_TOP_M = 0.2


def run_ago(*args: str) -> str:
    r = subprocess.run([sys.executable, "-m", "ago_runtime", *args], capture_output=True, text=True,
                       env={**os.environ, "AGO_NO_PROGRESS": "1"})
    if r.returncode != 0:
        raise SystemExit(f"ago {' '.join(args)} failed: {r.stderr.strip().splitlines()[-1:]}")
    return r.stdout


def gt_frames(town: Path, split: str | None = None):
    """(token, OccLabels) of a town's GT folder, optionally only the keyframes of `split` (splits.json)."""
    from ago_runtime.formats.occ3d_waymo import load_ground_truth
    from ago_runtime.scoring.cli import find_gt_files

    keep = None
    if split is not None:
        scenes = set(json.loads((town / "splits.json").read_text())[split])
        keep = lambda scene: scene in scenes   # noqa: E731
    for token, (scene, path) in sorted(find_gt_files(town / "gts").items()):
        if keep is None or keep(scene):
            yield token, load_ground_truth(path)[0]


def slab_labels(shape, range_min, voxel_size, ground_id: int, free_id: int) -> np.ndarray:
    z = range_min[2] + voxel_size[2] * (np.arange(shape[2]) + 0.5)
    out = np.full(tuple(shape), free_id, np.uint8)
    out[:, :, z < SLAB_TOP_M] = ground_id
    return out


def scene_prior(train_town: Path, names: list[str], free_id: int):
    """(labels, frames): each voxel's most frequent GT label over the train split of `train_town` (uint8)."""
    from ago_runtime.scoring.lidar_agreement import TrainingPrior

    prior = None
    for _, labels in gt_frames(train_town, "train"):
        if prior is None:
            prior = TrainingPrior(names[:free_id], free_id, labels.shape)
        prior.add(labels.semantics)
    return prior.labels().astype(np.uint8), prior.frames


def layer_counts(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, free_id: int) -> np.ndarray:
    """(3, Z) true positives, false positives, false negatives of occupancy (label != free) per z layer, over `mask`."""
    po, go = (pred != free_id) & mask, (gt != free_id) & mask
    return np.stack([(po & go).sum((0, 1)), (po & ~go).sum((0, 1)), (~po & go).sum((0, 1))]).astype(np.int64)


def above_ground_iou(counts: np.ndarray, range_min_z: float, voxel_z: float) -> float:
    """Occupancy IoU (%) over the layers whose centre is above the slab's top (SLAB_TOP_M): the geometry a flat
    ground predictor gets nothing of. NaN when those layers hold no occupied voxel in GT or prediction."""
    centres = range_min_z + voxel_z * (np.arange(counts.shape[1]) + 0.5)
    tp, fp, fn = counts[:, centres > SLAB_TOP_M].sum(1)
    return float(100 * tp / (tp + fp + fn)) if tp + fp + fn else float("nan")


def height_table(counts: np.ndarray, range_min_z: float, voxel_z: float) -> list[str]:
    """Markdown rows of the per-layer occupancy breakdown (layers with no GT or predicted occupied voxel skipped)."""
    tp, fp, fn = counts
    gt_total = max(int((tp + fn).sum()), 1)
    pct = lambda a, b: f"{100 * a / b:.1f}" if b else "n/a"   # noqa: E731
    rows = ["| z layer | z (m) | share of occupied GT | precision | recall | false positives | false negatives |",
            "|---:|---|---:|---:|---:|---:|---:|"]
    for k in range(counts.shape[1]):
        if tp[k] + fp[k] + fn[k] == 0:
            continue
        lo = range_min_z + k * voxel_z
        rows.append(f"| {k} | {lo:.1f} .. {lo + voxel_z:.1f} | {pct(tp[k] + fn[k], gt_total)} | {pct(tp[k], tp[k] + fp[k])} | "
                    f"{pct(tp[k], tp[k] + fn[k])} | {fp[k]} | {fn[k]} |")
    return rows


def cpu_line() -> str:
    from benchmarks.machine import cpu_model_and_flags

    model, flags = cpu_model_and_flags()
    keep = [f for f in flags if f.startswith(("avx512", "amx")) or f in ("avx2", "fma", "avx_vnni")]
    return f"{model}, {os.cpu_count()} CPUs; flags: {' '.join(keep)}"


def main(argv=None) -> dict:
    from ago_runtime.classes import OCC3D_NUSCENES
    from ago_runtime.geometry.grid import Grid
    from ago_runtime.predict.bundle import Bundle, resolve_bundle
    from ago_runtime.scoring.metric import OccupancyMetric

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--towns", nargs="+", required=True, help="datasets made by `ago synth` with unused seeds")
    ap.add_argument("--prior-data", required=True, help="the training town (its train split's GT makes the prior)")
    ap.add_argument("--bundle", default=None, help="default: the shipped default bundle")
    ap.add_argument("--prompts", default=str(REPO / "prompts/cw.txt"))
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/default_bundle_towns.md"))
    args = ap.parse_args(argv)
    bundle_dir = resolve_bundle(args.bundle)
    bundle = Bundle.load(bundle_dir)
    table = OCC3D_NUSCENES
    names = list(table.label_names)
    free_id, ground_id = table.free_index, names.index("driveable_surface")

    prior_labels, prior_frames = scene_prior(Path(args.prior_data), names, free_id)

    rows, started = [], time.time()
    heights, height_grid = None, None
    for town in map(Path, args.towns):
        with tempfile.TemporaryDirectory(prefix="ago-towns-") as tmp:
            pred, js = Path(tmp) / "pred", Path(tmp) / "metric.json"
            infer = ["infer", "--images", str(town), "--prompts", args.prompts, "--out", str(pred), "--picture", "none",
                     "--bundle", str(bundle_dir)]
            run_ago(*infer)
            run_ago("metric", "--pred", str(pred), "--gt", str(town / "gts"), "--json", str(js))
            m = json.loads(js.read_text())
            base = {k: OccupancyMetric(table=table) for k in ("all free", "ground slab", "scene prior")}
            layers = {k: 0 for k in ("bundle", *base)}
            for token, labels in gt_frames(town):
                grid = Grid.with_shape(labels.shape)
                mask = labels.mask_camera.astype(bool)
                with np.load(pred / f"{token}.npz") as z:
                    semantics = z["semantics"]
                preds = {"bundle": semantics, "all free": np.full(labels.shape, free_id, np.uint8),
                         "ground slab": slab_labels(labels.shape, grid.range_min, grid.voxel_size, ground_id, free_id),
                         "scene prior": prior_labels}
                for k, v in preds.items():
                    layers[k] = layers[k] + layer_counts(v, labels.semantics, mask, free_id)
                    if k in base:
                        base[k].update(v, labels.semantics, mask)
                height_grid = grid
        heights = layers["bundle"] if heights is None else heights + layers["bundle"]
        zmin, dz = float(height_grid.range_min[2]), float(height_grid.voxel_size[2])
        scores = {"bundle": (m["mIoU"], m["geometry_IoU"], above_ground_iou(layers["bundle"], zmin, dz))}
        scores.update({k: (100 * v.miou(), 100 * v.geometry_iou(), above_ground_iou(layers[k], zmin, dz))
                       for k, v in base.items()})
        rows.append((town, m["frames"], scores, {c: m["iou"].get(c) for c in names[:free_id]}))

    cmd = "python -m benchmarks.default_bundle_towns " + " ".join(argv if argv is not None else sys.argv[1:])
    from ago_runtime.predict.bundle import card_line

    ckpt = bundle.contract.checkpoint
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    fmt = lambda v: "nan" if v is None or v != v else f"{v:.2f}"   # noqa: E731
    lines = [
        "# The default bundle on towns it never saw, beside predictors that look at no image", "",
        f"Command: `{cmd}` ({time.time() - started:.0f} s; commit {commit}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}).",
        f"Bundle: `{bundle_dir}` exported from checkpoint sha256 `{ckpt.sha256}` (step {ckpt.step}); "
        f"{card_line(bundle)}.",
        f"Scene prior: each voxel's most frequent GT label over the {prior_frames} train-split keyframes of "
        f"`{args.prior_data}`. Every score over the GT camera mask, Occ3D metric at the GT's 200x200x16.",
        f"CPU: {cpu_line()}.", "",
        f"Each cell: mIoU / geometry IoU / geometry IoU above the ground (occupancy IoU over the layers whose centre "
        f"is above z = {SLAB_TOP_M} m, where the slab has nothing).", "",
        "| town | frames | bundle | all free | ground slab | scene prior |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    keys = ("all free", "ground slab", "scene prior")
    cell = lambda v: " / ".join(fmt(x) for x in v)   # noqa: E731
    for town, frames, s, _ in rows:
        lines.append(f"| {town.name} | {frames} | **{cell(s['bundle'])}** | " + " | ".join(cell(s[k]) for k in keys)
                     + " |")
    mean = lambda k, i: float(np.nanmean([r[2][k][i] for r in rows]))   # noqa: E731
    lines.append("| mean | | **" + cell([mean("bundle", i) for i in range(3)]) + "** | "
                 + " | ".join(cell([mean(k, i) for i in range(3)]) for k in keys) + " |")
    lines += ["", "Per-class IoU of the bundle:", "",
              "| town | " + " | ".join(names[:free_id]) + " |", "|---|" + "---:|" * free_id]
    for town, _, _, iou in rows:
        lines.append(f"| {town.name} | " + " | ".join(fmt(iou[c]) for c in names[:free_id]) + " |")
    lines += ["", "Where the bundle's occupancy is right and wrong, by height (all towns together; over the GT camera "
              "mask):", "", *height_table(heights, float(height_grid.range_min[2]), float(height_grid.voxel_size[2]))]
    best = [max(keys, key=lambda k: np.nan_to_num(mean(k, i), nan=-1.0)) for i in range(3)]
    lines += ["", "Best no-image predictor, by mean: " + "; ".join(
        f"{what}: {b} ({mean(b, i):.2f} against the bundle's {mean('bundle', i):.2f})"
        for i, (what, b) in enumerate(zip(("mIoU", "geometry IoU", "geometry IoU above the ground"), best))) + "."]
    text = "\n".join(lines) + "\n"
    from ago_runtime.atomic import write_text

    write_text(args.out, text)
    print(text)
    return {"rows": [(str(t), s) for t, _, s, _ in rows]}


if __name__ == "__main__":
    main()
