"""The real chain, measured (issue 35): a real nuScenes scene through every verb, scored against its LiDAR.

    nice -n 10 python benchmarks/real_chain.py [--data ../shared/data/nuscenes-scene] [--work work/real_chain] \
        [--steps 2000] [--keyframes 3] [--cut TRAIN,VAL] [--out benchmarks/results/real_chain_kf3.md] [--json FILE]

With `--cut TRAIN,VAL` the chain runs on WORK/data, a cut of the one-scene dataroot made by
benchmarks/dataroot_cut.py: its first TRAIN keyframes are split "train", the next VAL split "val", as two
scenes with a splits.json, so pseudo-labels of train frames never superimpose a val frame. `--cut 22,8`
holds out the last 8 of the 30 default training keyframes (recipe selection, real_chain_select.py);
`--cut 30,11` is the default split without that neighbour overlap (the test run).

Stages, each an `ago` subprocess as a user would run it (wall time and peak RSS from /usr/bin/time):
1. `ago pseudo-labels --segmenter boxes --split train` (labels from the dataset's own 3D boxes + LiDAR
   ground; no VLM; without splits.json "train" is the first 3/4 of the scene's keyframes: 30 of 41),
   `--keyframes` keyframes superimposed per pseudo-label;
2. `ago train --config cpu` on them (`--set max_steps=STEPS`; the trainer's own loop; resumes);
3. `ago export --parity-frame DATA --readout-grid 200x200x16`;
4. `ago infer` of the new bundle on the "val" keyframes (the other 11), and of the shipped synthetic
   bundle on the same frames;
5. `ago metric --lidar DATA --prior WORK/pseudo` of both (docs/metric_and_pictures.md): the primary measures
   (object ray IoU, non-ground ray IoU at 1/2/4 m, judged-voxel F1) beside every no-image baseline and the
   training-frame prior (benchmarks/real_chain_lidar_metric.py renders them), and the first measures (depth
   error along the LiDAR rays, LiDAR hits in occupied voxels, occupied voxels the LiDAR saw through), which
   the recipe selection (real_chain_select.py) was declared on and which a constant can win.
Writes a markdown file with the command, per-stage time and memory, both bundles' measures, whether the
real-trained model beats the synthetic one on all three, and the per-keyframe costs scaled to nuScenes'
28,130 training keyframes. Every stage reuses what an interrupted run left (pseudo-labels and training
resume; export, infer and metric are redone).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

from ago_runtime.atomic import write_text  # noqa: E402

NUSCENES_KEYFRAMES = 28130   # nuScenes trainval keyframes (700 + 150 scenes)
MEASURES = (("depth_error_mean_m", "depth error mean (m)", "lower"),
            ("depth_error_median_m", "depth error median (m)", "lower"),
            ("lidar_hits_in_occupied_pct", "LiDAR hits in occupied (%)", "higher"),
            ("occupied_seen_free_pct", "occupied seen free (%)", "lower"),
            ("rays_no_occupied_pct", "rays meeting no occupied voxel (%)", "lower"))
TARGETS = ("depth_error_median_m", "lidar_hits_in_occupied_pct", "occupied_seen_free_pct")


def threads_prefix() -> str:
    """`OMP_NUM_THREADS=n ` when the run was limited to n torch/OpenMP threads (part of the command), else ""."""
    n = os.environ.get("OMP_NUM_THREADS")
    return f"OMP_NUM_THREADS={n} " if n else ""


def last_logged_step(log_jsonl: Path) -> int:
    """The last step in a training log.jsonl (0 when there is none)."""
    if not log_jsonl.is_file():
        return 0
    lines = [ln for ln in log_jsonl.read_text().splitlines() if ln.strip()]
    return int(json.loads(lines[-1]).get("step", 0)) if lines else 0


def run_stage(name: str, args: list[str], work: Path, log) -> dict:
    """`python -m ago_runtime ARGS` under /usr/bin/time; its stdout/stderr go to work/<name>.log."""
    timing = work / f"{name}.time"
    cmd = ["/usr/bin/time", "-f", "%e %M", "-o", str(timing), sys.executable, "-m", "ago_runtime", *args]
    log(f"== {name}: ago {' '.join(shlex.quote(str(a)) for a in args)}")
    t = time.perf_counter()
    with open(work / f"{name}.log", "w") as out:
        r = subprocess.run(cmd, stdout=out, stderr=subprocess.STDOUT, env={**os.environ, "AGO_NO_PROGRESS": "1"})
    if r.returncode != 0:
        tail = (work / f"{name}.log").read_text().strip().splitlines()[-3:]
        raise SystemExit(f"stage {name} failed (exit {r.returncode}): {tail}")
    wall, rss_kb = timing.read_text().split()[-2:]
    shown = [str(a) for a in args if str(a) != "--sample"]
    samples = len(shown) - len([a for a in shown if len(a) != 32 or not a.isalnum()])
    shown = [a for a in shown if len(a) != 32 or not a.isalnum()] + ([f"--sample <{samples} val tokens>"] if samples else [])
    res = {"stage": name, "seconds": round(float(wall), 1), "peak_rss_mb": round(int(rss_kb) / 1024),
           "command": "ago " + " ".join(shlex.quote(a) if not a.startswith("--sample <") else a for a in shown)}
    log(f"   {res['seconds']} s, {res['peak_rss_mb']} MB (wall in this script {time.perf_counter() - t:.1f} s)")
    return res


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(REPO.parent / "shared/data/nuscenes-scene"), help="nuScenes dataroot")
    ap.add_argument("--work", default=str(REPO / "work/real_chain"))
    ap.add_argument("--steps", type=int, default=2000, help="training steps")
    ap.add_argument("--keyframes", type=int, default=3, help="pseudo-labels: keyframes superimposed "
                    "(benchmarks/results/real_chain.md compares 1, 3 and 10)")
    ap.add_argument("--cut", default=None, metavar="TRAIN,VAL", help="run on a cut of the dataroot: its first "
                    "TRAIN keyframes as split train, the next VAL as split val (benchmarks/dataroot_cut.py)")
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/real_chain_kf3.md"))
    ap.add_argument("--json", default=None, help="also write the stages and measures as JSON here")
    args = ap.parse_args(argv)
    from ago_runtime.formats.nuscenes import NuScenesDataset

    data, work = Path(args.data), Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    source = data
    if args.cut:
        from benchmarks.dataroot_cut import cut_dataroot
        n_train, n_val = (int(v) for v in args.cut.split(","))
        cut_dataroot(source, work / "data", n_train, n_val)
        data = work / "data"
    ds = NuScenesDataset(data, load_images=False, load_extras=False)
    train, val = ds.split("train"), ds.split("val")
    val_tokens = [ds.sample_tokens[i] for i in val]
    stages = []

    def log(s):
        print(s, flush=True)

    stages.append(run_stage("pseudo_labels", ["pseudo-labels", "--data", data, "--out", work / "pseudo",
                                              "--segmenter", "boxes", "--split", "train",
                                              "--keyframes", str(args.keyframes)], work, log))
    done = [ln for ln in (work / "pseudo_labels.log").read_text().splitlines() if ln.startswith("pseudo-labels:")]
    if done and " 0 already there" not in done[-1]:
        stages[-1]["note"] = f"resumed: {done[-1].split(' -> ')[0]} (the wall time is this run's part only)"
    from benchmarks.real_chain_lidar_metric import lidar_tables
    from benchmarks.run_settings import asked_config, check_reuse, trained_settings

    train_sets = [f"data={data}", f"pseudo={work / 'pseudo'}", f"out={work / 'train'}", f"max_steps={args.steps}"]
    check_reuse(work / "train", asked_config("cpu", train_sets))   # a run trained otherwise is refused, not resumed
    resume = ["--resume"] if (work / "train" / "last.pt").is_file() else []
    start_step = last_logged_step(work / "train" / "log.jsonl") if resume else 0
    stages.append(run_stage("train", ["train", "--config", "cpu", "--data", data, "--pseudo", work / "pseudo",
                                      "--out", work / "train", "--set", f"max_steps={args.steps}", *resume], work, log))
    if resume:
        stages[-1]["note"] = (f"resumed from last.pt (log at step {start_step} when resumed): the wall time covers "
                              "only the steps after the last checkpoint")
    stages.append(run_stage("export", ["export", work / "train" / "last.pt", "-o", work / "bundle",
                                       "--parity-frame", data, "--readout-grid", "200x200x16", "--train-bank-only"],
                            work, log))
    sample_args = [a for t in val_tokens for a in ("--sample", t)]
    results, per_frame, lidar = {}, {}, {}
    for name, bundle in (("real", ["--bundle", work / "bundle"]), ("synthetic", [])):
        pred = work / f"pred_{name}"
        stages.append(run_stage(f"infer_{name}", ["infer", "--images", data, *bundle, *sample_args, "--out", pred,
                                                  "--picture", "none"], work, log))
        stages.append(run_stage(f"metric_{name}", ["metric", "--pred", pred, "--lidar", data, "--allow-missing",
                                                   "--prior", work / "pseudo", "--json", work / f"metric_{name}.json"],
                                work, log))
        scored = json.loads((work / f"metric_{name}.json").read_text())["lidar"]
        results[name], per_frame[name] = scored["overall"], scored.get("per_frame")
        lidar[name] = scored
    card = (work / "infer_real.log").read_text().splitlines()[0]
    trained = trained_settings(work / "train", "cpu")

    def better(key, how):
        a, b = results["real"][key], results["synthetic"][key]
        return a is not None and b is not None and (a < b if how == "lower" else a > b)

    wins = {key: better(key, how) for key, _, how in MEASURES}
    by = {s["stage"]: s for s in stages}
    pl_per = by["pseudo_labels"]["seconds"] / max(1, len(train))
    inf_per = by["infer_real"]["seconds"] / max(1, len(val))
    command = threads_prefix() + "nice -n 10 python benchmarks/real_chain.py " + " ".join(shlex.quote(str(a)) for a in (argv or sys.argv[1:]))
    if args.cut:
        split_text = (f"a cut of `{source}` made by benchmarks/dataroot_cut.py: its first {len(train)} keyframes are "
                      f"split train, the next {len(val)} split val, two scenes with a splits.json, so no train "
                      f"pseudo-label superimposes a val keyframe")
    else:
        split_text = (ds.split_note("train") or "train split from splits.json") + "; val = " + \
                     (ds.split_note("val") or "val split from splits.json")
    lines = [
        "# The real chain on one nuScenes scene (issue 35)", "",
        f"Command: `{command}` ({time.strftime('%Y-%m-%d')}, this 2-core CPU shared with other work; niced).", "",
        f"Data: `{data}` ({len(ds)} keyframes; {split_text}). Pseudo-labels from the dataset's 3D boxes + LiDAR ground (`--segmenter boxes`, no "
        f"VLM, no image embeddings), `ago train --config cpu` for {args.steps} steps, export, `ago infer` on the "
        f"{len(val)} val keyframes, `ago metric --lidar` (docs/metric_and_pictures.md).", "",
        f"Bundle card of the real-trained model: `{card}`", "",
        "Trained with (the run's config.json where it differs from the `cpu` preset; a run trained otherwise is "
        f"refused, not resumed): {', '.join(f'`{t}`' for t in trained)}.", "",
        "| stage | wall (s) | peak RSS (MB) | command |", "|---|---:|---:|---|",
        *[f"| {s['stage']} | {s['seconds']} | {s['peak_rss_mb']} | `{s['command']}` |" for s in stages], "",
        *[f"- {s['stage']}: {s['note']}" for s in stages if s.get("note")], "",
        f"## LiDAR measures on the {len(val)} val keyframes, beside the no-image baselines", "",
        *lidar_tables(lidar, {"real": "real-trained (boxes)", "synthetic": "shipped synthetic bundle"}), "",
        "## The first LiDAR measures (diagnostics: a constant can win them; real_chain_select.py's rule used them)", "",
        "| measure | real-trained (boxes) | shipped synthetic bundle | better |", "|---|---:|---:|---|",
        *[f"| {label} | {results['real'][key]} | {results['synthetic'][key]} | "
          f"{'real' if wins[key] else 'synthetic / tie'} ({how}) |" for key, label, how in MEASURES], "",
        f"Target (the real-trained model beats the synthetic bundle on depth error, hits in occupied and occupied "
        f"seen free): **{'met' if all(wins[k] for k in TARGETS) else 'not met'}** "
        f"({', '.join(k for k in TARGETS if not wins[k]) or 'all three better'}).", "",
        "## At nuScenes scale", "",
        f"Per keyframe here: pseudo-labels {pl_per:.2f} s ({args.keyframes} keyframes superimposed, keyframe LiDAR "
        f"only), inference {inf_per:.2f} s (including the bundle load, over {len(val)} frames). nuScenes trainval "
        f"has {NUSCENES_KEYFRAMES} keyframes; with `--shard K/N` on N such machines (2 cores each), no coordination:",
        "", "| machines N | pseudo-labels (h) | inference (h) |", "|---:|---:|---:|",
        *[f"| {n} | {NUSCENES_KEYFRAMES * pl_per / n / 3600:.1f} | {NUSCENES_KEYFRAMES * inf_per / n / 3600:.1f} |"
          for n in (1, 8, 32, 128)], "",
        "Real nuScenes also has ~9 non-key sweeps per keyframe (`--sweeps`), which the trimmed extract lacks; "
        "they add lifting work per keyframe, so the pseudo-label column is a lower bound.", "",
    ]
    write_text(Path(args.out), "\n".join(lines))
    log(f"wrote {args.out}")
    summary = {"command": command, "data": str(data), "train_frames": len(train), "val_frames": len(val),
               "keyframes": args.keyframes, "steps": args.steps, "stages": stages, "results": results,
               "per_frame": per_frame, "wins": wins, "target_met": all(wins[k] for k in TARGETS), "card": card,
               "trained_with": trained}
    if args.json:
        write_text(Path(args.json), json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    main()
