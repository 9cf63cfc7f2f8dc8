"""Seed repeats of experiment runs: how much of a table's difference is run-to-run noise?

Takes an experiments folder made by `ago experiments run --profile cpu --out DIR`, retrains the named
closed-world runs with other seeds (same config, only `seed` changed; resumable; under
`DIR/extra/seed<s>/<run>`), scores them like the experiments (cw view) and writes a table of mIoU and
geometry IoU per run and seed, with the seed-0 numbers from the experiments beside them.

    python -m benchmarks.seed_repeat --exp data/exp --runs cw/ago cw/ago-no-occ --seeds 1
        -> benchmarks/results/seed_repeat.md
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("AGO_NO_PROGRESS", "1")
RESULTS = REPO / "benchmarks" / "results" / "seed_repeat.md"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--exp", type=Path, default=Path("data/exp"))
    ap.add_argument("--runs", nargs="+", default=["cw/ago", "cw/ago-no-occ"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[1])
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()

    from ago_runtime.atomic import write_json, write_text
    from ago_runtime.vocab.prompts import resolve_prompt_file
    from ago_train.experiments.driver import EXPERIMENTS, ExperimentRunner, runs_for
    from ago_train.experiments.plan import ExperimentProfile
    from ago_train.experiments.view_eval import View, evaluate_views
    from ago_train.trainer import train

    runner = ExperimentRunner(ExperimentProfile.preset("cpu"), args.exp, quiet=True)
    specs = {s.name: s for e in EXPERIMENTS for s in runs_for(e, runner.profile)}
    rows = []
    for name in args.runs:
        spec = specs.get(name)
        if spec is None or spec.setting != "cw":
            raise SystemExit(f"{name}: not a closed-world run of the experiments ({sorted(n for n in specs if n.startswith('cw/'))})")
        base = json.loads((runner.run_dir(name) / "views.json").read_text())["views"]["cw"]
        rows.append((name, 0, base["mIoU"], base["geometry_IoU"], "experiments"))
        for seed in args.seeds:
            out = args.exp / "extra" / f"seed{seed}" / name
            cfg = dataclasses.replace(runner.train_config(spec), seed=seed, out=str(out))
            t0 = time.time()
            if not (out / "done.json").is_file():
                train(cfg, resume=(out / "last.pt").is_file(), quiet=True)
                write_json(out / "done.json", {"seed": seed, "wall_s": round(time.time() - t0)})
            if not (out / "views.json").is_file():
                r = evaluate_views(out / "last.pt", str(runner.data), [View("cw", str(resolve_prompt_file("cw")))])
                r.pop("kept")
                write_json(out / "views.json", r)
            v = json.loads((out / "views.json").read_text())["views"]["cw"]
            rows.append((name, seed, v["mIoU"], v["geometry_IoU"], str(out)))
    L = ["# Seed repeats of closed-world experiment runs", "",
         f"Command: `python -m benchmarks.seed_repeat --exp {args.exp} --runs {' '.join(args.runs)} "
         f"--seeds {' '.join(map(str, args.seeds))}`  ",
         "Same config as the experiments' run (profile cpu: 300 steps, 72 synthetic train frames), only the "
         "training seed (model init, noise words, voxel samples, frame order) changed; scored on the 24 val "
         "frames (cw label space, F_3D only).", "",
         "| run | seed | mIoU | geometry IoU | folder |", "|---|---|---|---|---|"]
    L += [f"| {n} | {s} | {m} | {g} | {f} |" for n, s, m, g, f in rows]
    write_text(args.out, "\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
