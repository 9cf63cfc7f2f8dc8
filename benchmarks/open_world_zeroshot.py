"""Zero-shot open world on the synthetic benchmark: grounding alone vs AGO, identifiers, seeds, adapter diagnostics.

    python -m benchmarks.open_world_zeroshot --data DATASET \
        --run grounding:0=RUN_DIR --run grounding:1=RUN_DIR --run ago:0=RUN_DIR --run ago:1=RUN_DIR \
        [--run "ago, no centring:0=RUN_DIR"] [--snapshots] [--max-frames N] \
        [--out benchmarks/results/open_world_zeroshot.md] [--figure docs/figures/entropy_per_class.png]

Every RUN_DIR is an `ago train` folder of the open-world pretraining (prompts/ow_pretrain.txt, 5
classes). Each checkpoint is scored on the val split with the 15-class prompts/ow.txt (known = the
classes the 5 pretraining classes cover, unknown = barrier, traffic cone, terrain, manmade,
vegetation), from one forward pass per frame (ago_train.experiments.view_eval.evaluate_views), under
the identifiers "none" (F_3D only), "max-conf", "min-entropy" (AGO's) and "adapted" (F~_3D only).
Runs named `METHOD:SEED` are averaged per method (each seed shown). Per run also: how class-specific
the adapted embedding is — the class margin (per GT class, cos to its own class text minus the mean
cos to the other class texts, averaged over the unknown classes) of F~_3D and F_3D — its
nearest-text accuracy on unknown-class voxels (of the GT voxels of unknown classes that the model
calls occupied, the share whose class under the adapted branch alone is the right one), and the mean
entropy of P and P~ per unknown class. With --snapshots the same diagnostics are taken at every
snapshot of each run (the adapter over training). Writes a markdown table with the command and the
per-class entropy figure of the first AGO method (mean over its seeds).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from ago_runtime.atomic import atomic_path, write_json, write_text  # noqa: E402

IDS = ("none", "max-conf", "min-entropy", "adapted")


def known_prompts(out_dir: Path) -> Path:
    from ago_train.open_world import OpenWorldConfig, known_prompt_file
    from ago_train.train_config import TrainConfig

    return known_prompt_file(OpenWorldConfig(base=TrainConfig(), pseudo_pretrain="", pseudo_full=""), out_dir)


def unknown_diagnostics(result: dict) -> dict:
    """Class margins, nearest-text accuracy and entropies over the unknown classes of one scored checkpoint."""
    stats = result["stats"]
    classes, known = stats["classes"], set(stats["known"])
    unk = [i for i, c in enumerate(classes) if c not in known]
    out = {}
    for key, name in (("cos_adapted", "margin_adapted"), ("cos_main", "margin_main")):
        c = np.asarray(stats[key], dtype=np.float64)
        k = len(c)
        off = (c.sum(1) - np.diag(c)) / (k - 1)
        out[name] = float(np.mean((np.diag(c) - off)[unk]))
    out["entropy_main"] = {classes[i]: stats["entropy_main"][i] for i in unk}
    out["entropy_adapted"] = {classes[i]: stats["entropy_adapted"][i] for i in unk}
    for view, name in (("adapted", "nn_acc_adapted"), ("none", "nn_acc_main")):
        m = result["views"][view]["metric"]
        conf = np.asarray(m["confusion"], dtype=np.float64)
        free = int(m["free_index"])
        occ = [j for j in range(conf.shape[1]) if j != free]
        called = conf[np.ix_(unk, occ)].sum()
        out[name] = float(conf[unk, unk].sum() / called) if called else float("nan")
    return out


def score(ckpt: Path, data: str, prompts: Path, cache: Path, max_frames) -> dict:
    st = ckpt.stat()
    stamp = f"{st.st_size}:{st.st_mtime_ns}"   # a cached score is reused only for the same checkpoint file
    if cache.is_file():
        cached = json.loads(cache.read_text())
        if cached.get("checkpoint_stamp") in (stamp, None):
            return cached
    from ago_train.experiments.view_eval import View, evaluate_views

    views = [View(i, str(prompts), i) for i in IDS]
    r = evaluate_views(ckpt, data, views, stats_view="min-entropy", max_frames=max_frames, quiet=True)
    r.pop("kept")
    slim = {"views": {k: {"mIoU": v["mIoU"], "subsets": v["subsets"], "geometry_IoU": v["geometry_IoU"],
                          "metric": {"confusion": v["metric"]["confusion"], "free_index": v["metric"]["free_index"],
                                     "iou": v["metric"]["iou"]}}
                      for k, v in r["views"].items()},
            "stats": r["stats"]}
    slim["diag"] = unknown_diagnostics(slim)
    slim["checkpoint_stamp"] = stamp
    write_json(cache, slim)
    return slim


def split_miou(view: dict, classes: list[str]) -> float | None:
    """Mean IoU (%) of `classes` from a view's per-class IoUs (classes absent from GT and prediction,
    None there, are left out, as in the metric's own means)."""
    vals = [view["metric"]["iou"].get(c) for c in classes]
    vals = [v for v in vals if v is not None]
    return round(float(np.mean(vals)), 2) if vals else None


def fmt(vals: list[float], digits: int = 2) -> str:
    vals = [v for v in vals if v is not None]
    if not vals:
        return "–"
    if len(vals) == 1:
        return f"{vals[0]:.{digits}f}"
    return f"{np.mean(vals):.{digits}f} ({', '.join(f'{v:.{digits}f}' for v in vals)})"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--run", action="append", required=True, help="METHOD:SEED=RUN_DIR")
    ap.add_argument("--snapshots", action="store_true")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/open_world_zeroshot.md"))
    ap.add_argument("--figure", default=str(REPO / "docs/figures/entropy_per_class.png"))
    args = ap.parse_args(argv)
    runs = []
    for spec in args.run:
        label, _, path = spec.rpartition("=")
        method, _, seed = label.rpartition(":")
        runs.append((method or label, seed, Path(path)))
    out_dir = Path(args.out).parent
    prompts = known_prompts(Path(runs[0][2]))
    from ago_runtime.progress import track

    scored = {}
    for method, seed, run in track(runs, "scoring runs", total=len(runs)):
        ckpts = [run / "last.pt"]
        if args.snapshots:
            ckpts = sorted((run / "snapshots").glob("step_*.pt")) or ckpts
        per = {}
        for ck in ckpts:
            cache = run / "zeroshot" / f"{ck.stem}{'' if args.max_frames is None else f'_f{args.max_frames}'}.json"
            per[ck.stem] = score(ck, args.data, prompts, cache, args.max_frames)
        scored[(method, seed)] = per
    by_method = defaultdict(list)
    for (method, seed), per in scored.items():
        by_method[method].append((seed, per[list(per)[-1]]))

    from ago_train.open_world import paper_split

    pk, pu = paper_split("ow", "ow_pretrain")
    cmd = "python -m benchmarks.open_world_zeroshot " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    L = [f"# Zero-shot open world (pretrain on 5 classes, score on 15): grounding vs AGO", "",
         f"Command: `{cmd}`", "",
         f"Val split of `{args.data}`{'' if args.max_frames is None else f' (first {args.max_frames} frames)'}; "
         "Occ3D metric over the camera mask; unknown classes: barrier, traffic cone, terrain, manmade, "
         "vegetation. Mean over seeds, each seed in brackets.", "",
         f"The last two columns use the paper's split (its Tab. 2 zero-shot rows): known = {', '.join(pk)} "
         f"({len(pk)}); unknown = the other {len(pu)}, the refined vehicle and cycle classes included.", "",
         "| method | identifier | known mIoU | unknown mIoU | mIoU (15) | known, paper split | unknown, paper split |",
         "|---|---|---:|---:|---:|---:|---:|"]
    for method, items in by_method.items():
        for ident in IDS:
            vs = [r["views"][ident] for _, r in items]
            if method.startswith("grounding") and ident != "none":
                continue
            L.append(f"| {method} | {ident} | {fmt([v['subsets']['known'] for v in vs])} | "
                     f"{fmt([v['subsets']['unknown'] for v in vs])} | {fmt([v['mIoU'] for v in vs])} | "
                     f"{fmt([split_miou(v, pk) for v in vs])} | {fmt([split_miou(v, pu) for v in vs])} |")
    L += ["", "Adapter diagnostics on the unknown classes (last checkpoint): class margin of F~_3D and F_3D, "
          "nearest-text accuracy of the adapted and the main branch on unknown-class voxels called occupied, "
          "and the entropy of P and P~ (nats; calibrated logits, softmax over the 15 classes; per unknown class the mean over "
          "its visible voxels, then the mean over the 5 classes).", "",
          "| method | margin F~_3D | margin F_3D | nearest-text acc. F~ | nearest-text acc. F | entropy P | entropy P~ | "
          "unknown classes with H(P~) < H(P) |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for method, items in by_method.items():
        d = [r["diag"] for _, r in items]
        lower = [sum(d_["entropy_adapted"][c] < d_["entropy_main"][c] for c in d_["entropy_main"]) for d_ in d]
        L.append(f"| {method} | {fmt([x['margin_adapted'] for x in d], 4)} | {fmt([x['margin_main'] for x in d], 4)} | "
                 f"{fmt([x['nn_acc_adapted'] for x in d], 3)} | {fmt([x['nn_acc_main'] for x in d], 3)} | "
                 f"{fmt([float(np.mean(list(x['entropy_main'].values()))) for x in d], 3)} | "
                 f"{fmt([float(np.mean(list(x['entropy_adapted'].values()))) for x in d], 3)} | "
                 f"{', '.join(f'{n}/5' for n in lower)} |")
    if args.snapshots:
        L += ["", "Over training (each run's snapshots):", "",
              "| run | checkpoint | unknown mIoU (min-entropy) | unknown mIoU (adapted) | margin F~_3D | nearest-text acc. F~ |",
              "|---|---|---:|---:|---:|---:|"]
        for (method, seed), per in scored.items():
            for stem, r in per.items():
                L.append(f"| {method}:{seed} | {stem} | {r['views']['min-entropy']['subsets']['unknown']} | "
                         f"{r['views']['adapted']['subsets']['unknown']} | {r['diag']['margin_adapted']:.4f} | "
                         f"{r['diag']['nn_acc_adapted']:.3f} |")
    text = "\n".join(L) + "\n"
    write_text(args.out, text)
    ago = [(m, r) for m, items in by_method.items() for _, r in items if not m.startswith("grounding")]
    if ago and args.figure:
        from ago_runtime.pictures.charts import bar_chart
        import cv2

        m = ago[0][0]
        seeds = [r for mm, r in ago if mm == m]          # the first AGO method, averaged over its seeds
        st = seeds[0]["stats"]
        known = set(st["known"])
        h_main = np.mean([r["stats"]["entropy_main"] for r in seeds], axis=0).tolist()
        h_adap = np.mean([r["stats"]["entropy_adapted"] for r in seeds], axis=0).tolist()
        img = bar_chart(f"Entropy per GT class, P (F_3D) vs P~ (F~_3D), zero-shot, mean of {len(seeds)} seed(s)",
                        st["classes"], [("P (F_3D)", h_main, (180, 119, 31)),
                                        ("P~ (F~_3D)", h_adap, (14, 127, 255))],
                        [c not in known for c in st["classes"]], "entropy (nats)")
        with atomic_path(args.figure) as tmp:
            cv2.imwrite(str(tmp), img)
    print(text)
    return {"scored": {f"{m}:{s}": per for (m, s), per in scored.items()}}


if __name__ == "__main__":
    main()
