"""Score what `scripts/train_real.sh DATAROOT OUT` made on its held-out test keyframes (issue 47).

    python benchmarks/train_real.py --run OUT [--curve] [--metric-path DIR] [--out benchmarks/results/train_real.md]

Reads OUT/train_real.json (the settings, the split, the stage times, the val scores and the chosen length)
and OUT/work/real (the split dataroot), then, on the test keyframes only (the last of each scene, never
trained on nor used to choose):
1. `ago infer` of OUT/bundle (the trained bundle) and of the shipped synthetic bundle (no --bundle);
2. with --curve: `ago export` + `ago infer` of every other snapshot of OUT/work/train (the learning curve);
3. `ago metric --pred P --lidar OUT/work/real --allow-missing --prior OUT/work/real-pseudo-train --json` of each,
   whose JSON holds the LiDAR measures of the prediction and of the no-image baselines (all free, all occupied,
   slabs, bowl, the training-frame prior), scored with the same rays;
and writes the tables (primary measures, vehicles per class, the learning curve, the stage times) into --out
between its part written before the run and a "## Reading" part written by hand (both kept). `--metric-path DIR` runs `ago metric` from another checkout (a branch
whose metric is not merged yet); every other verb runs from this one. `--export-only` exports the snapshots
there are and stops (it reads no test keyframe, so the curve's exports may run beside the training). Predictions and scores stay in
OUT/bench/ and are reused when there (delete it to redo).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ago_runtime.atomic import write_text  # noqa: E402

PRIMARY = (("object_ray_iou", "object ray IoU (%)"), ("geometry_ray_iou_nonground@1", "non-ground ray IoU @1 m"),
           ("geometry_ray_iou_nonground@2", "@2 m"), ("geometry_ray_iou_nonground@4", "@4 m"),
           ("voxel_f1_pct", "voxel F1 (%)"))
VEHICLES = ("car", "truck", "bus", "trailer", "construction_vehicle", "bicycle", "motorcycle", "pedestrian")
MARKER = "## Results (written by benchmarks/train_real.py)"
READING = "## Reading (written by hand after the run)"


def ago(args: list, log: Path, pythonpath: str | None = None) -> float:
    """`python -m ago_runtime ARGS` from this checkout, or from `pythonpath` (run there: `-m` puts the working
    folder first on the path), its output appended to `log`; paths are made absolute."""
    env = {**os.environ, "AGO_NO_PROGRESS": "1", "PYTHONPATH": pythonpath or str(REPO)}
    args = [a.resolve() if isinstance(a, Path) else a for a in args]
    t = time.perf_counter()
    with open(log, "a") as f:
        f.write(f"$ ago {' '.join(shlex.quote(str(a)) for a in args)}\n")
        f.flush()
        r = subprocess.run([sys.executable, "-m", "ago_runtime", *[str(a) for a in args]], stdout=f,
                           stderr=subprocess.STDOUT, env=env, cwd=pythonpath or REPO)
    if r.returncode:
        raise SystemExit(f"ago {args[0]} failed (exit {r.returncode}); see {log}")
    return time.perf_counter() - t


def export_snapshot(snapshot: Path, bundle: Path, readout_grid: str, real: Path, log: Path) -> None:
    """`ago export` of a snapshot as `ago train-real` exports its chosen one (under a temporary name, renamed)."""
    import shutil

    tmp = bundle.with_name(bundle.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    ago(["export", snapshot, "-o", tmp, "--readout-grid", readout_grid, "--train-bank-only", "--parity-frame", real], log)
    os.replace(tmp, bundle)


def predict_and_score(name: str, bundle: Path | None, real: Path, tokens: list[str], prior: Path | None, bench: Path,
                      metric_path: str | None) -> dict:
    """Infer `bundle` (None: the shipped synthetic one) on the test tokens and score them against the LiDAR (with the
    prior baseline from `prior`'s pseudo-labels when given)."""
    pred, js = bench / f"pred_{name}", bench / f"metric_{name}.json"
    if not js.is_file():
        if not (pred / "done").is_file():
            ago(["infer", "--images", real, *(["--bundle", bundle] if bundle else []),
                 *[a for t in tokens for a in ("--sample", t)], "--out", pred, "--picture", "none"], bench / "bench.log")
            (pred / "done").write_text("")
        ago(["metric", "--pred", pred, "--lidar", real, "--allow-missing", *(["--prior", prior] if prior else []), "--json", js],
            bench / "bench.log", metric_path)
    return json.loads(js.read_text())["lidar"]


def fmt(v) -> str:
    return "n/a" if v is None else f"{v:.2f}" if isinstance(v, float) else str(v)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", required=True, help="the OUT folder of scripts/train_real.sh")
    ap.add_argument("--curve", action="store_true", help="also export and score every other snapshot")
    ap.add_argument("--metric-path", default=None, help="run `ago metric` from this checkout (PYTHONPATH)")
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/train_real.md"))
    ap.add_argument("--export-only", action="store_true", help="only export the snapshots there are (for --curve; "
                    "reads no test keyframe, so it may run while the training does)")
    args = ap.parse_args(argv)
    run = Path(args.run)
    work, real = run / "work", run / "work" / "real"
    bench = run / "bench"
    if args.export_only:
        bench.mkdir(exist_ok=True)
        from ago_train.train_real import RealRecipe

        grid = RealRecipe().readout_grid
        for snap in sorted((work / "train" / "snapshots").glob("step_*.pt")):
            if not (bench / f"bundle_{snap.stem[5:]}").is_dir():
                export_snapshot(snap, bench / f"bundle_{snap.stem[5:]}", grid, real, bench / "bench.log")
        return
    rec = json.loads((run / "train_real.json").read_text())
    split = json.loads((real / "split.json").read_text())
    tokens = [t for parts in split["scenes"].values() for t in parts["test"]]
    bench.mkdir(exist_ok=True)
    prior = work / "real-pseudo-train"
    chosen = rec["select"]["chosen_step"]
    scored = {"trained": predict_and_score("trained", run / "bundle", real, tokens, prior, bench, args.metric_path),
              "synthetic": predict_and_score("synthetic", None, real, tokens, prior, bench, args.metric_path)}
    curve = {chosen: scored["trained"]}
    if args.curve:
        for step in rec["train"]["snapshot_steps"]:
            if step == chosen:
                continue
            b = bench / f"bundle_{step:06d}"
            if not b.is_dir() and not (bench / f"metric_step{step}.json").is_file():
                export_snapshot(work / "train" / "snapshots" / f"step_{step:06d}.pt", b, rec["recipe"]["readout_grid"],
                                real, bench / "bench.log")
            curve[step] = predict_and_score(f"step{step}", b, real, tokens, prior, bench, args.metric_path)

    preds = scored["trained"]["predictors"]
    baselines = scored["trained"]["baselines"]
    rows = [("trained bundle (`ago train-real`, step %d)" % chosen, preds["prediction"]),
            ("shipped synthetic bundle", scored["synthetic"]["predictors"]["prediction"])]
    rows += [(f"{b} (no image)", preds[b]) for b in baselines]
    short = ["synthetic bundle", *baselines]
    beaten = {k: [n for n, (_, m) in zip(short, rows[1:]) if m.get(k) is not None
                  and (preds["prediction"].get(k) is None or m[k] >= preds["prediction"][k])] for k, _ in PRIMARY}
    veh = [c for c in VEHICLES if any(m.get("object_ray_iou_per_class", {}).get(c, {}).get("@1") is not None
                                      for _, m in rows[:2])]
    load = rec.get("load_average_start"), rec.get("load_average_end")
    try:
        cpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        model = next((ln.split(":", 1)[1].strip() for ln in cpu.splitlines() if ln.startswith("Model name")), "?")
    except OSError:
        model = platform.processor() or "?"
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    lines = [MARKER, "",
             f"Commands: `{'OMP_NUM_THREADS=' + rec['omp_num_threads'] + ' ' if rec.get('omp_num_threads') else ''}"
             f"bash scripts/train_real.sh {rec['dataroot']} {run}` then "
             f"`python benchmarks/train_real.py {' '.join(shlex.quote(a) for a in (argv or sys.argv[1:]))}` "
             f"({time.strftime('%Y-%m-%d')}, commit {commit}; `ago metric` from "
             f"{args.metric_path or 'this checkout'}).", "",
             f"Settings the run trained with (`train_real.json` recipe; each an `ago train-real` option or default): "
             f"`{json.dumps(rec['recipe'], sort_keys=True)}`.", "",
             f"Machine: {model}, 2 cores shared with five other engineers' work; load average at the start "
             f"{load[0]}, at the end {load[1]}.", "",
             "### Stage times of the run", "", "| stage | wall (s) | note |", "|---|---:|---|",
             *[f"| {k} | {v['seconds']} | {v.get('note', '')} |" for k, v in rec["stages"].items()],
             f"| **total** | **{rec['seconds_total']}** ({rec['seconds_total'] / 60:.1f} min) | this invocation's "
             "stages (a resumed run's earlier part is not in it) |", "",
             f"Training: {rec['train']['real_frames']} real train keyframes and {rec['train']['town_frames']} synthetic "
             f"town frames, sources {json.dumps([{k: s[k] for k in ('weight', 'split')} for s in rec['train']['sources']])} "
             f"(real first), `{rec['recipe']['preset']}` preset, {rec['recipe']['steps']} steps.", "",
             "### The length, chosen on the val keyframes (before the test block was read)", "",
             "| step | val mIoU | val geometry IoU | (mIoU + geometry IoU) / 2 |", "|---:|---:|---:|---:|",
             *[f"| {s}{' **chosen**' if int(s) == chosen else ''} | {v['mIoU']} | {v['geometry_IoU']} | "
               f"{(v['mIoU'] + v['geometry_IoU']) / 2:.2f} |" for s, v in rec["select"]["scores"].items()], "",
             f"### LiDAR measures on the {len(tokens)} test keyframes (`ago metric --lidar`, all higher is better)", "",
             "| predictor | " + " | ".join(label for _, label in PRIMARY) + " |", "|---|" + "---:|" * len(PRIMARY),
             *[f"| {n} | " + " | ".join(fmt(m.get(k)) for k, _ in PRIMARY) + " |" for n, m in rows], "",
             "Baselines: " + "; ".join(f"{b} = {d}" for b, d in baselines.items()) + ".", "",
             "Predictors at or above the trained bundle, per measure: "
             + "; ".join(f"{label}: {', '.join(v) if v else 'none'}" for (k, label), v in zip(PRIMARY, beaten.values())) + ".", "",
             "### Object ray IoU per class (%, @1 m / @2 m / @4 m) on the test keyframes", "",
             "| class | trained bundle | shipped synthetic bundle |", "|---|---|---|",
             *[f"| {c} | " + " | ".join(" / ".join(fmt(m["object_ray_iou_per_class"][c].get(f"@{t}")) for t in (1, 2, 4))
                                        for _, m in rows[:2]) + " |" for c in veh], ""]
    if len(curve) > 1:
        lines += ["### Learning curve on the test keyframes (each snapshot exported and scored; for reading only, "
                  "the length was chosen on val)", "",
                  "| step | " + " | ".join(label for _, label in PRIMARY) + " |", "|---:|" + "---:|" * len(PRIMARY),
                  *[f"| {s}{' (chosen)' if s == chosen else ''} | "
                    + " | ".join(fmt(curve[s]["predictors"]["prediction"].get(k)) for k, _ in PRIMARY) + " |"
                    for s in sorted(curve)], ""]
    notes = scored["trained"].get("notes") or []
    lines += [f"Note from `ago metric`: {n}" for n in notes]
    out = Path(args.out)
    text = out.read_text() if out.is_file() else ""
    head = text.split(MARKER)[0].rstrip() + "\n\n" if text else ""
    tail = ("\n" + READING + text.split(READING, 1)[1]) if READING in text else ""   # written by hand: kept
    write_text(out, head + "\n".join(lines) + "\n" + tail)
    write_text(bench / "summary.json", json.dumps({"tokens": tokens, "scored": {k: v["predictors"] for k, v in scored.items()},
                                                    "curve": {str(s): c["predictors"]["prediction"] for s, c in curve.items()}},
                                                   indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
