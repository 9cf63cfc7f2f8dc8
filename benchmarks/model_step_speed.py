"""Time a training step (forward + backward) of a model preset on this machine, with random inputs.

    python -m benchmarks.model_step_speed --preset cpu [--voxels 8000] [--threads 2] [--steps 5] [--set k=v ...]
        [--out benchmarks/results/model_step_speed.md]

`--voxels M` runs the voxel heads on a sample of M voxels (as training does with
ago_train.losses.sampling.select_training_voxels); 0 = the full grid. Prints the median step time
and its parts (backbone+FPN, TPV encoder, voxel heads + a dummy loss, backward) in seconds, plus
the step's process CPU time (step_cpu_s; with --threads 1 it is what an idle machine's wall time
would be, even while other jobs share the cores). `--out FILE` also writes them as a markdown results
file with the command, the commit, the CPU and the load average. (The whole trainer's step on real
frames and pseudo-labels: benchmarks/train_step_speed.py.)
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from ago_runtime.atomic import write_text
from ago_runtime.geometry.camera import Rig
from ago_train.model.aggregate import planes_at_voxels, planes_to_voxels
from ago_train.model.config import ModelConfig


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--voxels", type=int, default=8000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--pretrained", action="store_true", help="load ImageNet weights (same speed)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="override integer config fields, e.g. --set frozen_stages=2 tpv_dim=48")
    ap.add_argument("--out", default=None, help="also write a markdown results file here")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    cfg = ModelConfig.preset(args.preset)
    cfg.pretrained = args.pretrained and cfg.pretrained
    for item in args.set:
        key, value = item.split("=", 1)
        setattr(cfg, key, int(value))
    cfg.validate()
    model = cfg.build().train()
    images = torch.randn(1, cfg.num_cameras, 3, cfg.image_height, cfg.image_width)
    ego2img = torch.from_numpy(Rig.nuscenes_like(cfg.image_width, cfg.image_height).ego2img())[None]
    index = None
    if args.voxels:
        index = torch.randperm(model.num_voxels)[: args.voxels][None]

    rows = []
    for _ in range(args.steps + 1):
        c0 = time.process_time()
        t0 = time.perf_counter()
        B, V = images.shape[:2]
        feats = model.fpn(model.backbone(images.reshape(B * V, *images.shape[2:])))
        t1 = time.perf_counter()
        planes = model.encoder(feats, ego2img)
        t2 = time.perf_counter()
        vox = planes_to_voxels(planes, model.grid_shape) if index is None else \
            planes_at_voxels(planes, model.grid_shape, index)
        feat = model.decoder_out(model.decoder(vox))
        adapted = model.adapter_out(model.adapter(feat))
        loss = feat.square().mean() + adapted.square().mean()
        t3 = time.perf_counter()
        loss.backward()
        t4 = time.perf_counter()
        model.zero_grad(set_to_none=True)
        rows.append((t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0, time.process_time() - c0))
    rows = rows[1:]  # the first step warms up
    med = [statistics.median(r[i] for r in rows) for i in range(6)]
    result = {"preset": args.preset, "voxels": args.voxels or model.num_voxels, "threads": args.threads,
              "backbone_fpn_s": med[0], "encoder_s": med[1], "heads_s": med[2], "backward_s": med[3],
              "step_s": med[4], "step_cpu_s": med[5]}
    line = " ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in result.items())
    print(line)
    if args.out:
        write_text(args.out, results_markdown(line, args.steps, argv))
    return result


def results_markdown(line: str, steps: int, argv) -> str:
    """The results file: what ran, where, and the medians."""
    repo = Path(__file__).resolve().parents[1]
    git = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=repo)
    cpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    model = next((ln.split(":", 1)[1].strip() for ln in cpu.splitlines() if ln.startswith("Model name")), "?")
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    args = sys.argv[1:] if argv is None else list(argv)
    return "\n".join([
        "# One training step of a model preset, random inputs (benchmarks/model_step_speed.py)", "",
        f"Command: `python -m benchmarks.model_step_speed {shlex.join(args)}`; commit {git.stdout.strip() or '?'}; "
        f"CPU {model} ({os.cpu_count()} cores), torch {torch.__version__}; load average {load} at the end "
        "(other jobs may share the machine: step_cpu_s is the process CPU time, which they do not inflate at "
        "--threads 1).", "",
        f"Median over {steps} steps after one warm-up step, seconds:", "", "    " + line, ""])


if __name__ == "__main__":
    main()
