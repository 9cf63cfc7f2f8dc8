"""Does the modality adapter learn class directions with more training? (diagnostic; benchmarks/results/adapter_training_length.md)

Takes an experiments folder made by `ago experiments run --profile cpu --out DIR` (its data and its
`ow/ago` run of the profile's length), trains the same open-world `ago` run for longer (same config,
only max_steps changed; resumable), scores both with the experiments' views and writes a table:
zero-shot known / unknown / all mIoU with the min-entropy identifier and with the adapted branch alone,
the adapted branch's mean entropy, and how class-specific F~_3D is: per GT class, cos(F~_3D, own class
text) minus the mean cos to the other classes' texts (E_3D of the simulated VLM beside it).

    python -m benchmarks.adapter_training_length --exp data/exp --steps 1200
        -> benchmarks/results/adapter_training_length.md
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("AGO_NO_PROGRESS", "1")
RESULTS = REPO / "benchmarks" / "results" / "adapter_training_length.md"


def margin(cos: list[list[float]]) -> float:
    """Mean over classes of cos(own text) - mean cos(other texts)."""
    c = np.asarray(cos, dtype=np.float64)
    k = len(c)
    off = (c.sum(1) - np.diag(c)) / (k - 1)
    return float(np.mean(np.diag(c) - off))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--exp", type=Path, default=Path("data/exp"))
    ap.add_argument("--steps", type=int, default=1200)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()

    from ago_runtime.atomic import write_json, write_text
    from ago_train.experiments.driver import ExperimentRunner, views_for
    from ago_train.experiments.plan import ExperimentProfile, ow_run
    from ago_train.experiments.view_eval import evaluate_views
    from ago_train.trainer import train

    runner = ExperimentRunner(ExperimentProfile.preset("cpu"), args.exp, quiet=True)
    spec = ow_run("ago")
    base = runner.run_dir(spec.name)
    if not (base / "views.json").is_file():
        raise SystemExit(f"{base}/views.json missing: run `ago experiments run tab2 --profile cpu --out {args.exp}` first")
    long_dir = args.exp / "extra" / f"ow-ago-{args.steps}steps"
    cfg = dataclasses.replace(runner.train_config(spec), max_steps=args.steps, out=str(long_dir),
                              ckpt_every=max(50, args.steps // 4))
    t0 = time.time()
    if not (long_dir / "done.json").is_file():
        train(cfg, resume=(long_dir / "last.pt").is_file(), quiet=True)
        (long_dir / "done.json").write_text(json.dumps({"steps": args.steps, "wall_s": round(time.time() - t0)}))
    ow_prompts = str(args.exp / "ow_known.txt")
    views = views_for(spec, ow_prompts)
    scored = {f"{runner.profile.steps} steps (ow/ago)": json.loads((base / "views.json").read_text())}
    path = long_dir / "views.json"
    if not path.is_file():
        r = evaluate_views(long_dir / "last.pt", str(runner.data), views, stats_view="ow-min-entropy", quiet=True)
        r.pop("kept")
        write_json(path, r)
    scored[f"{args.steps} steps"] = json.loads(path.read_text())
    gap = json.loads((args.exp / "data_scores.json").read_text())["gap_e3d"]
    cw_names = gap["classes"]
    ow_names = scored[next(iter(scored))]["stats"]["classes"]
    idx = [cw_names.index(c) for c in ow_names]
    e3d = np.asarray(gap["cos"])[np.ix_(idx, idx)]

    L = ["# Does the adapter learn class directions with more training?", "",
         f"Command: `python -m benchmarks.adapter_training_length --exp {args.exp} --steps {args.steps}`  ",
         f"Data: the `cpu` experiments profile's synthetic city (72 train frames, 24 val frames), open-world "
         f"pretraining on ow_pretrain (5 classes), zero-shot on ow (15 classes: 10 known, 5 unknown).  ",
         "Simulated VLM embeddings (E_3D) — a simulation, docs/synth.md.", "",
         "| run | min-entropy known | unknown | all | adapted-only known | unknown | all | mean entropy P | mean entropy P~ | "
         "class margin of F~_3D | class margin of F_3D |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in scored.items():
        v, a, s = r["views"]["ow-min-entropy"], r["views"]["ow-adapted"], r["stats"]
        w = np.asarray(s["voxels"], dtype=np.float64)
        L.append(f"| {name} | {v['subsets']['known']} | {v['subsets']['unknown']} | {v['mIoU']} | "
                 f"{a['subsets']['known']} | {a['subsets']['unknown']} | {a['mIoU']} | "
                 f"{np.average(s['entropy_main'], weights=w):.3f} | {np.average(s['entropy_adapted'], weights=w):.3f} | "
                 f"{margin(s['cos_adapted']):.4f} | {margin(s['cos_main']):.4f} |")
    L += ["", f"For reference, the simulated VLM embeddings themselves (E_3D, val frames): class margin "
          f"{margin(e3d.tolist()):.4f} over the same 15 classes.", "",
          "Class margin: per GT class, cos(embedding, own class text) minus the mean cos to the other 14 class "
          "texts, averaged over classes (0 = no class information; E_3D's margin is what a perfect adapter "
          "would reach). Entropies are voxel-weighted means over the visible GT-occupied voxels, in nats "
          "(uniform over 16 labels = 2.77).", ""]
    write_text(args.out, "\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
