"""Open-vocabulary retrieval scored as POP-3D scores it: average precision of the voxel ranking per phrase.

    python -m benchmarks.retrieval_ap --bundle BUNDLE --data DATASET [--split val] \
        [--prompts prompts/ow.txt] [--known-from prompts/ow_pretrain.txt] [--max-frames N] \
        [--out benchmarks/results/retrieval_ap.md]

For every class of the prompt file, the voxels are ranked by the similarity `ago retrieve` computes
(cosine between the voxel's adapted embedding F~_3D and the class's phrase embeddings, max over its
phrases; `ago_runtime.predict.heads.phrase_similarity`; `--branch identifier|main` for the other choices). As in POP-3D, where the ranked items are
LiDAR points, the ranked items are the GT-occupied voxels inside the GT camera mask (at the GT
resolution; the model grid is upsampled by nearest neighbour), pooled over the frames; the positives
are the voxels of the class's Occ3D ids. Per class: AP and the class's prevalence (the expected AP of
a random ranking). Classes the `--known-from` prompt file covers are marked known (the open-world
bundle trained on them); the target (issue "Open world that works") is the mean AP over the unknown
classes >= 3x their mean prevalence. Writes a markdown table with the command.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from ago_runtime.atomic import write_text  # noqa: E402
from ago_runtime.vocab.bank import load_prompt_bank  # noqa: E402
from ago_runtime.classes import FREE  # noqa: E402
from ago_runtime.predict.heads import phrase_similarity  # noqa: E402
from ago_runtime.scoring.metric import upsample_nearest  # noqa: E402
from ago_runtime.formats.nuscenes import NuScenesDataset  # noqa: E402
from ago_runtime.predict.predictor import Predictor  # noqa: E402
from ago_runtime.progress import track  # noqa: E402
from ago_runtime.vocab.prompts import parse_prompt_file  # noqa: E402
from ago_runtime.scoring.ranking import average_precision  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--prompts", default=str(REPO / "prompts/ow.txt"))
    ap.add_argument("--known-from", default=str(REPO / "prompts/ow_pretrain.txt"))
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--branch", choices=("adapted", "identifier", "main"), default="adapted",
                    help="whose embedding is compared with the phrase: the adapted branch everywhere (what "
                         "`ago retrieve` does), the identifier's choice per voxel, or the main branch")
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/retrieval_ap.md"))
    args = ap.parse_args(argv)

    predictor = Predictor(args.bundle)
    b = predictor.bundle
    bank = load_prompt_bank(args.prompts)
    space = parse_prompt_file(args.prompts)
    covered = {i for c in parse_prompt_file(args.known_from).classes for i in c.occ3d_ids}
    K = bank.num_classes
    ds = NuScenesDataset(args.data, load_extras=False)
    indices = ds.split(args.split) if args.split != "all" else list(range(len(ds)))
    indices = indices[: args.max_frames] if args.max_frames else indices
    sims = [[] for _ in range(K)]
    gts = []
    for i in track(indices, "retrieval similarity", total=len(indices)):
        f = ds[i]
        h, g = predictor.encode_arrays(*predictor.prepare(f.images, f.rig, str(args.data)))
        pred = predictor.predict_hidden(h, g, bank, b.identifier)
        gt = f.gt
        factor = tuple(a // s for a, s in zip(gt.semantics.shape, b.grid.shape))
        keep = gt.mask_camera.astype(bool) & (gt.semantics != FREE)
        branch = {"identifier": pred.branch.reshape(-1), "adapted": np.ones(h.shape[0], np.uint8),
                  "main": np.zeros(h.shape[0], np.uint8)}[args.branch]
        for k in range(K):
            emb = bank.embeddings[bank.phrase_class == k]
            sim = phrase_similarity(b.heads, h, g, branch, emb).reshape(b.grid.shape)
            sims[k].append(upsample_nearest(sim, factor)[keep])
        gts.append(gt.semantics[keep].astype(np.int16))
    c = np.concatenate(gts)
    rows, unknown_ap, unknown_prev = [], [], []
    for k, cls in enumerate(space.classes):
        positive = np.isin(c, list(cls.occ3d_ids))
        prevalence = float(positive.mean())
        if not positive.any():
            rows.append((cls.name, "-", 0, float("nan"), 0.0))
            continue
        ap_k = average_precision(np.concatenate(sims[k]), positive)
        known = bool(cls.occ3d_ids) and set(cls.occ3d_ids) <= covered
        rows.append((cls.name, "known" if known else "unknown", int(positive.sum()), ap_k, prevalence))
        if not known:
            unknown_ap.append(ap_k)
            unknown_prev.append(prevalence)
    mean_ap = float(np.mean(unknown_ap)) if unknown_ap else float("nan")
    mean_prev = float(np.mean(unknown_prev)) if unknown_prev else float("nan")
    cmd = "python -m benchmarks.retrieval_ap " + " ".join(argv if argv is not None else sys.argv[1:])
    table = "\n".join(f"| {n} | {kind} | {cnt} | {100 * a:.2f} | {100 * p:.2f} | {a / p if p else float('nan'):.1f} |"
                      for n, kind, cnt, a, p in rows)
    ls = (b.card or {}).get("label_space") or {}
    trained = {"label_space": ls.get("name", "?") if isinstance(ls, dict) else ls}
    text = f"""# Open-vocabulary retrieval: average precision per phrase (POP-3D style)

Command: `{cmd}`

Bundle `{args.bundle}` (trained label space: {trained.get('label_space', '?')}), prompt file `{args.prompts}`,
{len(indices)} frames of `{args.data}` split `{args.split}`. Ranked: the {len(c)} GT-occupied voxels in the GT
camera mask; similarity on {'the identifier' + chr(39) + 's branch (' + b.identifier + ')' if args.branch == 'identifier' else 'the ' + args.branch + ' branch everywhere'}. "known" = covered by `{args.known_from}`.

| class | known / unknown | GT voxels | AP (%) | prevalence (%) | AP / prevalence |
|---|---|---:|---:|---:|---:|
{table}

**Unknown classes: mean AP {100 * mean_ap:.2f} %, mean prevalence {100 * mean_prev:.2f} %, ratio
{mean_ap / mean_prev if mean_prev else float('nan'):.2f}** (target >= 3).
"""
    write_text(args.out, text)
    print(text)
    return {"mean_ap_unknown": mean_ap, "mean_prevalence_unknown": mean_prev, "rows": rows}


if __name__ == "__main__":
    main()
