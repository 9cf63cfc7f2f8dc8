"""Where the zero-shot unknown-class IoU is lost: occupancy, the adapted branch, or the identifier.

    python -m benchmarks.open_world_ceiling --data DATASET --run NAME=RUN_DIR [--run ...] \
        [--max-frames N] [--out benchmarks/results/open_world_ceiling.md]

A DIAGNOSTIC (it reads the GT to route voxels, so it is never a rule anyone could ship). Each RUN_DIR is
an open-world pretraining run (prompts/ow_pretrain.txt); it is scored on the val split with the
15-class prompts/ow.txt as benchmarks/open_world_zeroshot.py does, one forward pass per frame, under:
- "none" (F_3D only), "min-entropy" (AGO's identifier), "adapted" (F~_3D for every occupied voxel);
- "oracle": the class of F~_3D where the GT voxel is of an unknown class, of F_3D elsewhere. This is
  the most any per-voxel choice between the two branches can give with this model's occupancy and
  these two branches: the identifier's ceiling;
- "oracle occupancy": the oracle, and GT-occupied voxels of unknown classes also counted occupied (the
  ceiling if the main branch never called unknown matter free).
Per unknown class also: of its GT voxels (camera mask), the share the main branch calls occupied, and
of those the share F~_3D / F_3D classify right (recall); and of the voxels F~_3D calls that class, the
share that are of that class in the GT (precision of the adapted branch on occupied voxels).
With --pseudo (the run's 5-class pseudo-labels), also on --train-frames training frames: the share of
labelled, hit-but-unlabelled (OCCUPIED_UNLABELLED) and free pseudo-label voxels the main branch calls
occupied (does the run fit its own occupancy targets?).
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]

from ago_runtime.atomic import write_text  # noqa: E402

VIEWS = ("none", "min-entropy", "adapted", "oracle", "oracle occupancy")


@torch.no_grad()
def score_run(ckpt_path: Path, data: str, prompts: str, max_frames: int | None) -> dict:
    from ago_runtime.geometry.preprocess import Preprocess
    from ago_runtime.scoring.metric import OccupancyMetric
    from ago_train.checkpoint import CheckpointContract
    from ago_train.dataset import FrameList, OccSampleDataset, collate
    from ago_train.evaluate import _to_gt_resolution, load_model
    from ago_train.experiments.view_eval import _bank
    from ago_train.model.text_logits import adapted_logits, class_logits, decide
    from ago_train.sources import open_split
    from ago_runtime.progress import track

    ckpt = CheckpointContract.load(ckpt_path, map_location="cpu")
    mcfg, model = load_model(ckpt, torch.device("cpu"), ckpt_path)
    scales = ckpt.scales
    stats = ckpt.adapted_stats
    bank = _bank(ckpt, prompts, False)
    space, K = bank.space, bank.space.num_classes
    unknown = np.array([c not in space.known for c in space.class_names])
    ds, indices = open_split(data, None, "val")
    indices = indices[:max_frames] if max_frames else indices
    grid = mcfg.grid_obj()
    pre = Preprocess(mcfg.image_width, mcfg.image_height)
    dataset = OccSampleDataset(FrameList(ds, indices), None, 17, grid, pre, gt_lut=np.arange(256, dtype=np.uint8),
                               with_gt=True)
    lut = space.gt_lut(free_index=K)
    metrics = {v: OccupancyMetric(list(space.class_names) + ["free"], free_index=K) for v in VIEWS}
    counts = {k: np.zeros(K, np.int64) for k in ("gt", "occupied", "adapted_right", "main_right",
                                                  "adapted_called", "adapted_called_right")}
    loader = torch.utils.data.DataLoader(dataset, batch_size=1, shuffle=False, collate_fn=collate)
    for batch in track(loader, description=f"ceiling {ckpt_path.parent.name}", total=len(loader)):
        out = model(batch["images"], batch["ego2img"])
        free = out.get("free_embedding", model.free_embedding)
        main = class_logits(out["feat"], bank.text, bank.phrase_class, K, free, None, free_bias=out.get("free_bias"))[0]
        adap = adapted_logits(out["feat_adapted"], bank.text, bank.phrase_class, K, free, stats)[0]
        tok = str(batch["token"][0])
        gt = lut[np.asarray(batch["gt"][0]).astype(np.uint8)]
        mask = np.asarray(batch["gt_mask"][0]).astype(bool)

        def up(labels: torch.Tensor) -> np.ndarray:
            return _to_gt_resolution(labels.numpy().reshape(grid.shape).astype(np.uint8), gt.shape, tok)

        lab = {v: up(decide(main, adap, v, K, scales).label) for v in ("none", "min-entropy", "adapted")}
        gt_unknown = (gt < K) & unknown[np.minimum(gt, K - 1)]
        lab["oracle"] = np.where(gt_unknown, lab["adapted"], lab["none"])
        adapted_class = up(adap[:, :K].argmax(-1))     # F~_3D's class everywhere (a positive scale keeps the argmax)
        lab["oracle occupancy"] = np.where(gt_unknown, adapted_class, lab["none"])
        for v in VIEWS:
            metrics[v].update(lab[v], gt, mask)
        occ = lab["none"] != K
        g = gt[mask]
        sel = g < K
        counts["gt"] += np.bincount(g[sel], minlength=K)[:K]
        m_occ = mask & occ & (gt < K)
        counts["occupied"] += np.bincount(gt[m_occ], minlength=K)[:K]
        counts["adapted_right"] += np.bincount(gt[m_occ & (lab["adapted"] == gt)], minlength=K)[:K]
        counts["main_right"] += np.bincount(gt[m_occ & (lab["none"] == gt)], minlength=K)[:K]
        m_called = mask & occ & (gt != K)       # GT-occupied voxels the model calls occupied
        counts["adapted_called"] += np.bincount(lab["adapted"][m_called], minlength=K + 1)[:K]
        counts["adapted_called_right"] += np.bincount(lab["adapted"][m_called & (lab["adapted"] == gt)],
                                                      minlength=K + 1)[:K]
    per_view = {}
    for v in VIEWS:
        iou = metrics[v].iou()
        per_view[v] = {c: (None if np.isnan(iou[i]) else 100 * float(iou[i]))
                       for i, c in enumerate(space.class_names)}
    cm = metrics["none"].confusion
    occupied_ratio = float(cm[:, :K].sum() / max(cm[:K, :].sum(), 1))   # predicted / GT occupied (camera mask)
    return {"classes": list(space.class_names), "unknown": [c for c, u in zip(space.class_names, unknown) if u],
            "geometry_IoU": 100 * metrics["none"].geometry_iou(), "occupied_ratio": occupied_ratio,
            "iou": per_view, "counts": {k: v.tolist() for k, v in counts.items()}, "frames": len(indices)}


@torch.no_grad()
def training_occupancy(ckpt_path: Path, data: str, pseudo: str, frames: int) -> dict:
    """Share of labelled / hit-but-unlabelled / free pseudo-label voxels of training frames called occupied."""
    from ago_runtime.classes import FREE, OCCUPIED_UNLABELLED
    from ago_runtime.geometry.preprocess import Preprocess
    from ago_train.checkpoint import CheckpointContract
    from ago_train.dataset import FrameList, OccSampleDataset, PseudoLabelSet, collate
    from ago_train.evaluate import bank_for, load_model
    from ago_train.model.text_logits import class_logits
    from ago_train.sources import open_split

    ckpt = CheckpointContract.load(ckpt_path, map_location="cpu")
    mcfg, model = load_model(ckpt, torch.device("cpu"), ckpt_path)
    space = ckpt.space
    K = space.num_classes
    text, pc = bank_for(ckpt, space)
    ds, idx = open_split(data, None, "train")
    idx = idx[:: max(1, len(idx) // frames)][:frames]
    dataset = OccSampleDataset(FrameList(ds, idx), PseudoLabelSet(pseudo), K, mcfg.grid_obj(),
                               Preprocess(mcfg.image_width, mcfg.image_height))
    tot = {"labelled": [0, 0], "hit, unlabelled": [0, 0], "free": [0, 0]}
    for i in range(len(dataset)):
        b = collate([dataset[i]])
        out = model(b["images"], b["ego2img"])
        lg = class_logits(out["feat"], text.float(), pc.long(), K, out.get("free_embedding", model.free_embedding),
                          free_bias=out.get("free_bias"))[0]
        occ = lg[:, : K + 1].argmax(-1) != K
        sem = b["semantics"][0]
        for name, sel in (("labelled", sem < K), ("hit, unlabelled", sem == OCCUPIED_UNLABELLED),
                          ("free", sem == FREE)):
            tot[name][0] += int(sel.sum())
            tot[name][1] += int((occ & sel).sum())
    return {k: (v[0], v[1] / max(v[0], 1)) for k, v in tot.items()}


def mean(vals):
    vals = [v for v in vals if v is not None]
    return float(np.mean(vals)) if vals else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--run", action="append", required=True, help="NAME=RUN_DIR (its last.pt is scored)")
    ap.add_argument("--prompts", default=None, help="evaluation prompt file with an @known line (default: "
                    "prompts/ow.txt with the known classes of the 5-class pretraining, as open_world_zeroshot.py)")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--pseudo", default=None, help="the runs' pretraining pseudo-labels: also measure training frames")
    ap.add_argument("--train-frames", type=int, default=6)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "open_world_ceiling.md"))
    args = ap.parse_args()
    if args.prompts is None:
        import tempfile

        from benchmarks.open_world_zeroshot import known_prompts
        args.prompts = str(known_prompts(Path(tempfile.mkdtemp(prefix="ago-ceiling-"))))
    lines = ["# Zero-shot open world: where the unknown-class IoU is lost (a diagnostic that reads the GT)", "",
             "Command: `python -m benchmarks." + Path(__file__).stem + " " + " ".join(shlex.quote(a) for a in sys.argv[1:])
             + "`", ""]
    for spec in args.run:
        name, _, run = spec.partition("=")
        r = score_run(Path(run) / "last.pt", args.data, args.prompts, args.max_frames)
        unk, classes = r["unknown"], r["classes"]
        known = [c for c in classes if c not in unk]
        lines += [f"## {name} (`{run}`, {r['frames']} val frames)", "",
                  f"Geometry IoU {r['geometry_IoU']:.2f}; predicted / GT occupied voxels in the camera mask "
                  f"{r['occupied_ratio']:.2f}.", "",
                  "| view | known mIoU | unknown mIoU | " + " | ".join(unk) + " |",
                  "|---|---:|---:|" + "---:|" * len(unk)]
        for v in VIEWS:
            iou = r["iou"][v]
            lines.append(f"| {v} | {mean([iou[c] for c in known]):.2f} | {mean([iou[c] for c in unk]):.2f} | "
                         + " | ".join("n/a" if iou[c] is None else f"{iou[c]:.2f}" for c in unk) + " |")
        c = {k: np.asarray(v) for k, v in r["counts"].items()}
        lines += ["", "| unknown class | GT voxels | called occupied | F~ right (of occupied) | F right | "
                  "precision of F~'s calls |", "|---|---:|---:|---:|---:|---:|"]
        for c_name in unk:
            i = classes.index(c_name)
            g, o = max(c["gt"][i], 1), max(c["occupied"][i], 1)
            lines.append(f"| {c_name} | {c['gt'][i]} | {100 * c['occupied'][i] / g:.1f} % | "
                         f"{100 * c['adapted_right'][i] / o:.1f} % | {100 * c['main_right'][i] / o:.1f} % | "
                         f"{100 * c['adapted_called_right'][i] / max(c['adapted_called'][i], 1):.1f} % "
                         f"({c['adapted_called'][i]} called) |")
        if args.pseudo:
            t = training_occupancy(Path(run) / "last.pt", args.data, args.pseudo, args.train_frames)
            lines += ["", f"Training frames ({args.train_frames}, pseudo-labels `{args.pseudo}`): share of the "
                      "pseudo-label voxels the main branch calls occupied: "
                      + "; ".join(f"{k} {100 * v[1]:.1f} % (of {v[0]})" for k, v in t.items()) + "."]
        lines.append("")
    write_text(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
