"""How well the runtime's "unexplained obstacle" score finds matter that no prompt explains (AUROC).

    python -m benchmarks.unexplained_obstacles --bundle BUNDLE --data DATASET [--split val] \
        [--prompts prompts/ow_pretrain.txt] [--max-frames N] [--out benchmarks/results/unexplained_obstacles.md] \
        [--choose-split train --choose-frames 40 --false-rate 0.05]

The bundle runs through the torch-free runtime (`Predictor.predict(..., volumes=True)`, what
`ago infer --save-volumes` writes) with a prompt file that names only some classes (default: the
5-class open-world pretraining file). Scored voxels: GT-occupied voxels inside the GT camera mask, at
the GT resolution (the model's grid is upsampled by nearest neighbour, as the Occ3D metric does).
Positives: voxels whose GT class no prompt class covers (e.g. manmade, vegetation, barrier for the
5-class file); negatives: voxels of the prompted classes. Reported: ROC AUC of the score
(`unexplained` = 1 - best prompted-class probability; target >= 0.75, issue "Open world that works")
and, for comparison, of the product p_occ x score (which also counts the model's geometry misses), the
average precision beside the positives' prevalence, and the share of positives and of negatives the
mask flags (p_occ > 0.5 and score > `ago_runtime.predict.predictor.UNEXPLAINED_THRESHOLD`), plus the mean
score per GT class. Writes a markdown table with the command.

--choose-split SPLIT: a mask threshold for this prompt file chosen on other frames by `ago choose-threshold`'s code
(ago_runtime.predict.threshold: the lowest threshold at which the mask flags at most --false-rate of the
prompted-class voxels of SPLIT, e.g. the training split, by its Occ3D GT), then the mask at that threshold on
--split beside the fixed one. The scored split is not looked at while choosing. With --choose-labels PSEUDO_DIR
the threshold is chosen as a user without GT chooses it, on those pseudo-labels of the same frames.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from ago_runtime.atomic import write_text  # noqa: E402
from ago_runtime.vocab.bank import load_prompt_bank  # noqa: E402
from ago_runtime.classes import FREE as OCC3D_FREE, OCC3D_CLASSES  # noqa: E402
from ago_runtime.scoring.metric import upsample_nearest  # noqa: E402
from ago_runtime.formats.nuscenes import NuScenesDataset  # noqa: E402
from ago_runtime.predict.predictor import UNEXPLAINED_THRESHOLD, Predictor, unexplained_mask  # noqa: E402
from ago_runtime.predict.frames import open_frames  # noqa: E402
from ago_runtime.predict.threshold import LabelFolder, choose_for_prompts  # noqa: E402
from ago_runtime.progress import track  # noqa: E402
from ago_runtime.vocab.prompts import parse_prompt_file  # noqa: E402
from ago_runtime.scoring.ranking import average_precision, roc_auc  # noqa: E402


def covered_occ3d_ids(prompt_file: str) -> set[int]:
    return {i for c in parse_prompt_file(prompt_file).classes for i in c.occ3d_ids}


def score_frames(predictor, bank, ds, indices, what: str):
    """-> (scores, occupancy, fixed-mask flags, GT classes) over the GT-occupied voxels in the GT camera mask of
    the frames `indices` (the model's grid upsampled to the GT's by nearest neighbour)."""
    scores, occs, flags, classes = [], [], [], []
    for i in track(indices, what, total=len(indices)):
        f = ds[i]
        pred = predictor.predict(f.images, f.rig, bank, volumes=True, source=str(ds.root))
        gt = f.gt
        factor = tuple(a // b for a, b in zip(gt.semantics.shape, pred.unexplained.shape))
        keep = gt.mask_camera.astype(bool) & (gt.semantics != OCC3D_FREE)
        scores.append(upsample_nearest(pred.unexplained, factor)[keep].astype(np.float32))
        occs.append(upsample_nearest(pred.occupancy, factor)[keep].astype(np.float32))
        flags.append(upsample_nearest(pred.unexplained_mask, factor)[keep])
        classes.append(gt.semantics[keep].astype(np.int16))
    return np.concatenate(scores), np.concatenate(occs), np.concatenate(flags), np.concatenate(classes)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--prompts", default=str(REPO / "prompts/ow_pretrain.txt"))
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/unexplained_obstacles.md"))
    ap.add_argument("--choose-split", default=None, help="choose the mask threshold on this split (see the doc)")
    ap.add_argument("--choose-frames", type=int, default=40, help="frames of --choose-split (spread over it)")
    ap.add_argument("--false-rate", type=float, default=0.05, help="share of prompted-class voxels the chosen "
                    "threshold may flag on --choose-split")
    ap.add_argument("--choose-labels", default=None, help="with --choose-split: choose on these labels (an `ago "
                    "pseudo-labels` folder, as `ago choose-threshold` does) instead of the split's GT")
    args = ap.parse_args(argv)
    if args.choose_split is not None and args.choose_split == args.split:
        ap.error("--choose-split must differ from --split (the scored frames are not used to choose)")

    predictor = Predictor(args.bundle)
    bank = load_prompt_bank(args.prompts)
    covered = covered_occ3d_ids(args.prompts)
    ds = NuScenesDataset(args.data, load_extras=False)
    indices = ds.split(args.split) if args.split != "all" else list(range(len(ds)))
    indices = indices[: args.max_frames] if args.max_frames else indices
    chosen = None
    if args.choose_split is not None:   # chosen first, on frames the scoring below never reads
        pool = ds.split(args.choose_split) if args.choose_split != "all" else list(range(len(ds)))
        pick = [pool[int(k)] for k in np.linspace(0, len(pool) - 1, min(args.choose_frames, len(pool)))]
        # `ago choose-threshold`'s own code, on the split's Occ3D GT or on --choose-labels (pseudo-labels)
        folder = LabelFolder.open(args.choose_labels or Path(args.data) / "gts")
        tokens = [ds.sample_tokens[i] for i in sorted(set(pick)) if ds.sample_tokens[i] in folder.files]
        if not tokens:
            ap.error(f"{folder.root} has no label of the picked {args.choose_split} frames")
        threshold = choose_for_prompts(predictor, bank, open_frames(args.data, tokens, rig=predictor.bundle.rig),
                                       folder, args.false_rate).threshold
        pick = tokens
        labels_used = (f"the pseudo-labels in {args.choose_labels}" if args.choose_labels else "its Occ3D GT") \
            + " (`ago choose-threshold`'s code)"
        chosen = {"split": args.choose_split, "frames": len(set(pick)), "false_rate": args.false_rate,
                  "threshold": threshold, "labels": labels_used}
    s, occ, flagged, c = score_frames(predictor, bank, ds, indices, "unexplained-obstacle score")
    positive = ~np.isin(c, sorted(covered))
    auc = roc_auc(s, positive)
    auc_product = roc_auc(occ * s, positive)
    ap_ = average_precision(s, positive)
    prevalence = float(positive.mean())
    tpr = float(flagged[positive].mean()) if positive.any() else float("nan")
    fpr = float(flagged[~positive].mean()) if (~positive).any() else float("nan")
    at_chosen = None
    if chosen is not None:
        at_chosen = unexplained_mask(s, occ, chosen["threshold"])
        chosen["tpr"] = float(at_chosen[positive].mean()) if positive.any() else float("nan")
        chosen["fpr"] = float(at_chosen[~positive].mean()) if (~positive).any() else float("nan")
    per_class = []
    for cid in sorted(set(c.tolist())):
        sel = c == cid
        per_class.append((OCC3D_CLASSES[cid], "prompted" if cid in covered else "absent", int(sel.sum()),
                          float(s[sel].mean()), float(flagged[sel].mean()),
                          float(at_chosen[sel].mean()) if at_chosen is not None else None))
    cmd = "python -m benchmarks.unexplained_obstacles " + " ".join(argv if argv is not None else sys.argv[1:])
    rows = "\n".join(f"| {n} | {kind} | {cnt} | {m:.3f} | {100 * fl:.1f} |"
                     + (f" {100 * fc:.1f} |" if fc is not None else "") for n, kind, cnt, m, fl, fc in per_class)
    chosen_text = ""
    if chosen is not None:
        chosen_text = (f"\nA threshold for this prompt file, chosen on {chosen['frames']} frames of split "
                       f"`{chosen['split']}` (not scored here), by {chosen['labels']}, as the lowest that flags at most "
                       f"{100 * chosen['false_rate']:g} % of its prompted-class voxels: **{chosen['threshold']:.3f}** "
                       f"(`ago infer --save-volumes --unexplained-threshold {chosen['threshold']:.3f}`). On the scored "
                       f"frames it flags {100 * chosen['tpr']:.1f} % of absent-class voxels and "
                       f"{100 * chosen['fpr']:.1f} % of prompted-class voxels (at {UNEXPLAINED_THRESHOLD}: "
                       f"{100 * tpr:.1f} % and {100 * fpr:.1f} %).\n")
    at_col = f" flagged at {chosen['threshold']:.3f} (%) |" if chosen is not None else ""
    at_sep = "---:|" if chosen is not None else ""
    text = f"""# Unexplained-obstacle score: AUROC on the synthetic world

Command: `{cmd}`

Bundle `{args.bundle}` ({(predictor.bundle.card.note or '') if predictor.bundle.card else ''}), prompt file
`{args.prompts}` ({bank.num_classes} classes), {len(indices)} frames of `{args.data}` split `{args.split}`.
Score per voxel: 1 - the largest probability a prompted class gets (max over the two branches), in
softmaxes over the prompted classes plus the bundle's training classes no prompt covers (reference
classes, ago_runtime/predict/heads.py, Predictor.fold_with_reference); mask: p_occ > 0.5 and score >
{UNEXPLAINED_THRESHOLD}. Scored: GT-occupied voxels in the GT camera mask ({len(s)} voxels); positives =
classes no prompt covers ({int(positive.sum())} voxels, prevalence {prevalence:.3f}).

| measure | value |
|---|---:|
| **ROC AUC of the score** (target >= 0.75) | **{auc:.3f}** |
| ROC AUC of p_occ x score (also counts GT-occupied voxels the model calls free) | {auc_product:.3f} |
| average precision of the score (random ranking = prevalence {prevalence:.3f}) | {ap_:.3f} |
| flagged by the mask: share of absent-class voxels | {100 * tpr:.1f} % |
| flagged by the mask: share of prompted-class voxels | {100 * fpr:.1f} % |
{chosen_text}
| GT class | in the prompt file | voxels | mean score | flagged (%) |{at_col}
|---|---|---:|---:|---:|{at_sep}
{rows}
"""
    write_text(args.out, text)
    print(text)
    return {"auroc": auc, "auroc_product": auc_product, "ap": ap_, "prevalence": prevalence, "tpr": tpr, "fpr": fpr,
            "chosen": chosen}


if __name__ == "__main__":
    main()
