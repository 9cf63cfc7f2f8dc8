"""Does a preset learn? Train it on a few frames through `ago train` and score it on those frames.

    python benchmarks/fit_check.py --config full                       # the paper's preset at 352x192 input
    python benchmarks/fit_check.py --config full --image-size 1600x928 --device cuda --frames 36 --steps 2000 \
        --snapshots 250,500,1000,2000 --train-voxels 0                 # the GPU check (docs/training.md)

1. Data (made once in --work, reused when there): `ago synth` renders a town of `--frames` keyframes on
   the preset's model grid (Occ3D GT), and `ago pseudo-labels` lifts closed-world pseudo-labels from the
   simulated segmenter and embedder (simulations, not a VLM) onto that grid.
2. Training: `ago train --config PRESET` with only the data, the input size, the length, the voxel sample
   and the snapshots changed (plus any --set): the trainer's own loop and learning-rate schedule, which
   are sized to --steps (a `note:` line says so).
3. At every snapshot, on the frames it trained on: the loss (log.jsonl), the feature spread and free
   share of F_3D over the whole grid (ago_train/fit_diagnostics.py), and `ago eval`'s geometry IoU and
   mIoU against the Occ3D GT (camera mask); beside them the pseudo-labels' own mIoU on the same frames,
   which is what the model is taught.
Writes --out (markdown, with the command) and a JSON and a PNG beside it. A model that predicts "all
free" scores geometry IoU 0 and free share 1.0, and its feature spread falls towards 0.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def ago(*args: str) -> None:
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "ago_runtime.cli", *args], text=True, capture_output=True,
                       env={**os.environ, "AGO_NO_PROGRESS": "1"})
    print(f"$ ago {' '.join(shlex.quote(a) for a in args)}  ({time.perf_counter() - t:.0f} s)", flush=True)
    for line in (r.stdout + r.stderr).splitlines():
        if line.startswith(("note:", "error:", "warning:")):
            print("  " + line, flush=True)
    if r.returncode != 0:
        sys.exit(f"failed (rc {r.returncode}):\n{r.stdout[-2000:]}\n{r.stderr[-4000:]}")


def prepare(work: Path, frames: int, grid: str, render: str) -> None:
    """The town and its pseudo-labels (skipped when already there)."""
    if not (work / "synth" / "splits.json").is_file():
        ago("synth", "--out", str(work / "synth"), "--scenes", "1", "--frames", str(frames), "--seed", "7",
            "--image-size", render, "--grid", grid, "--val-fraction", "0")
    if not (work / "pseudo" / "meta.json").is_file():
        ago("pseudo-labels", "--data", str(work / "synth"), "--out", str(work / "pseudo"), "--prompts", "cw",
            "--grid", grid, "--split", "train", "--segmenter", "sim", "--embedder", "sim",
            "--keyframes", "3", "--interval", "1")


def pseudo_miou(work: Path) -> float:
    """mIoU of the pseudo-labels against the GT of the same frames (benchmarks/pseudo_class_iou.py's rule)."""
    from benchmarks.pseudo_class_iou import pseudo_label_metric

    return 100.0 * pseudo_label_metric(work / "pseudo", work / "synth" / "gts").miou()


def grid_diagnostics(ckpt: Path, data: Path, device: str) -> dict:
    """Mean over the training frames of the whole-grid feature spread and free share of F_3D."""
    import torch

    from ago_train.checkpoint import CheckpointContract
    from ago_train.dataset import FrameList, OccSampleDataset
    from ago_train.evaluate import bank_for, load_model
    from ago_train.fit_diagnostics import feature_spread, free_share
    from ago_train.model.text_logits import class_logits
    from ago_train.sources import open_split
    from ago_runtime.geometry.preprocess import Preprocess

    dev = torch.device(device)
    state = CheckpointContract.load(ckpt, map_location="cpu")
    mcfg, model = load_model(state, dev, ckpt)
    space = state.space
    text, phrase_class = (t.to(dev) for t in bank_for(state, space))
    ds, indices = open_split(data, None, "train")
    items = OccSampleDataset(FrameList(ds, indices), None, space.num_classes, mcfg.grid_obj(),
                             Preprocess(mcfg.image_width, mcfg.image_height))
    spread, free = [], []
    with torch.no_grad():
        for i in range(len(items)):
            item = items[i]
            out = model(item["images"][None].to(dev), item["ego2img"][None].to(dev), adapted=False)
            logits = class_logits(out["feat"], text, phrase_class, space.num_classes, out["free_embedding"],
                                  free_bias=out.get("free_bias"))
            spread.append(feature_spread(out["feat"]))
            free.append(free_share(logits, space.num_classes))
    return {"feat_spread": float(np.mean(spread)), "free_share": float(np.mean(free))}


def plot(rows: list[dict], log: list[dict], path: Path, title: str) -> None:
    """Three charts side by side: the training loss, the batch's spread and free share, the scores."""
    import cv2

    from ago_runtime.pictures.charts import PALETTE, line_chart

    steps = [r["step"] for r in log]
    diag = [r for r in log if "feat_spread" in r]
    s = [r["step"] for r in rows]
    charts = [
        line_chart(f"{title}: loss", [("loss (training batch)", steps, [r["total"] for r in log], PALETTE[0])],
                   x_label="step", width=480, height=360),
        line_chart("training batch", [("feature spread", [r["step"] for r in diag], [r["feat_spread"] for r in diag], PALETTE[1]),
                                      ("free share", [r["step"] for r in diag], [r["free_share"] for r in diag], PALETTE[2])],
                   x_label="step", width=480, height=360, y_range=(0.0, 1.05)),
        line_chart("on its training frames (%)", [("geometry IoU", s, [r["geometry_IoU"] for r in rows], PALETTE[3]),
                                                   ("mIoU", s, [r["mIoU"] for r in rows], PALETTE[4])],
                   x_label="step", width=480, height=360),
    ]
    tmp = path.with_name(path.name + ".tmp.png")
    cv2.imwrite(str(tmp), cv2.hconcat(charts))
    os.replace(tmp, path)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="full", help="training preset (tiny, cpu, full)")
    ap.add_argument("--image-size", default="352x192", help="model input WIDTHxHEIGHT (multiples of 32)")
    ap.add_argument("--render-size", default=None, help="rendered camera size (default: the input's width, 16:9)")
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--steps", type=int, default=80)
    ap.add_argument("--snapshots", default="20,40,80")
    ap.add_argument("--train-voxels", type=int, default=8000, help="voxel sample per step (0 = the whole grid)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--work", type=Path, default=Path("work/fit_check"))
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--set", action="append", default=[], help="extra `ago train --set` (recorded in the results)")
    args = ap.parse_args(argv)

    from ago_runtime.geometry.grid import Grid
    from ago_train.train_config import TrainConfig

    preset = TrainConfig.preset(args.config)
    grid = "x".join(str(n) for n in Grid.from_dict(preset.model.grid).shape)
    width, height = (int(v) for v in args.image_size.lower().split("x"))
    render = args.render_size or f"{width}x{round(width * 9 / 16)}"
    snapshots = sorted({int(s) for s in args.snapshots.split(",") if s} | {args.steps})
    out = args.out or REPO / "benchmarks" / "results" / f"fit_check_{args.config}.md"
    work = args.work
    work.mkdir(parents=True, exist_ok=True)

    run = work / "run"
    sets = [f"data={work / 'synth'}", f"pseudo={work / 'pseudo'}", f"out={run}",
            f"model.image_width={width}", f"model.image_height={height}", f"train_voxels={args.train_voxels}",
            f"max_steps={args.steps}", f"epochs={math.ceil(args.steps / args.frames)}", "log_every=5",
            f"ckpt_every={max(args.steps // 4, 10)}", "num_workers=0", f"device={args.device}",
            f"feature_cache={work / 'cache'}", f"snapshot_steps={json.dumps(snapshots)}", *args.set]
    last = run / "snapshots" / f"step_{args.steps:06d}.pt"
    from benchmarks.run_settings import asked_config, check_reuse, trained_settings

    check_reuse(run, asked_config(args.config, sets))    # a run (its step_N.pt) trained otherwise is not reused
    t0 = time.perf_counter()
    prepare(work, args.frames, grid, render)
    t_data = time.perf_counter() - t0
    t1 = time.perf_counter()
    if not last.is_file():
        resume = ["--resume"] if (run / "last.pt").is_file() else []
        ago("train", "--config", args.config, *[a for s in sets for a in ("--set", s)], *resume)
    t_train = time.perf_counter() - t1
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]

    from ago_train.evaluate import evaluate

    rows = []
    for step in snapshots:
        ckpt = run / "snapshots" / f"step_{step:06d}.pt"
        res = evaluate(ckpt, work / "synth", split="train", identifier="none", device=args.device, quiet=True)
        near = min(log, key=lambda r: abs(r["step"] - step))
        rows.append({"step": step, "loss": near["total"], **grid_diagnostics(ckpt, work / "synth", args.device),
                     "geometry_IoU": res["geometry_IoU"], "mIoU": res["mIoU"]})
        print(json.dumps(rows[-1]), flush=True)
    pseudo = pseudo_miou(work)
    sec_step = float(np.median([r["sec_per_step"] for r in log[1:]] or [np.nan]))

    cmd = "python benchmarks/fit_check.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    min_spread = min(r.get("feat_spread", np.inf) for r in log)
    trained = trained_settings(run, args.config)
    lines = [f"# Fit check: the `{args.config}` preset on {args.frames} frames it trains on", "",
             f"Command: `{cmd}`", "",
             f"`ago train --config {args.config}` with {', '.join(f'`{s}`' for s in sets[3:])}; input "
             f"{width}x{height} (rendered {render}), model grid {grid}, device {args.device}. Pseudo-labels: "
             f"simulated segmenter and embedder (cw). Scored on the training frames against the Occ3D GT "
             f"(camera mask); spread and free share over the whole grid (ago_train/fit_diagnostics.py).", "",
             f"Trained with (the run's config.json where it differs from the `{args.config}` preset; a run trained "
             f"otherwise is refused, not reused): {', '.join(f'`{t}`' for t in trained)}.", "",
             "| step | loss | feature spread | free share | geometry IoU | mIoU |", "|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['step']} | {r['loss']:.3f} | {r['feat_spread']:.3f} | {r['free_share']:.3f} | "
                     f"{r['geometry_IoU']:.2f} | {r['mIoU']:.2f} |")
    lines += ["", f"Pseudo-labels' own mIoU on these frames: {pseudo:.2f} (the model's last mIoU is "
              f"{100 * rows[-1]['mIoU'] / max(pseudo, 1e-9):.0f} % of it).",
              f"Lowest feature spread of a logged training batch (every 5 steps): {min_spread:.3f}.",
              f"Time: data {t_data:.0f} s, training {t_train:.0f} s (median {sec_step:.1f} s a step; 0 s when "
              f"the run was already there), {time.perf_counter() - t0:.0f} s in all.", "",
              f"![curves]({out.with_suffix('.png').name})", ""]
    from ago_runtime.atomic import write_json, write_text

    write_text(out, "\n".join(lines))
    write_json(out.with_suffix(".json"), {"command": cmd, "sets": sets, "rows": rows, "pseudo_mIoU": pseudo,
                                          "log": log, "sec_per_step": sec_step})
    plot(rows, log, out.with_suffix(".png"), f"{args.config} preset, {args.frames} frames, {width}x{height}")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
