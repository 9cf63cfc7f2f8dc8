"""Training step time of the `cpu` preset in float32 and with `--set amp=bf16`, side by side (issue 52 item 4).

    python -m benchmarks.amp_bf16 --data DIR --pseudo DIR [--steps 20] [--warmup 3] [--out benchmarks/results/amp_bf16.md]

Two `Trainer`s of `TrainConfig.preset("cpu")` on the same frames and pseudo-labels (benchmarks/train_step_speed.py's
`make_trainer` and `Batches`), one with amp=bf16 (ago_train/amp.py: the forward under torch.autocast bfloat16, the
losses in float32). Same seed, so the same initial weights and batch order. Their steps alternate (fp32, bf16,
fp32, ...) so that the load of the shared machine weighs on both alike; the median of `--steps` steps after
`--warmup` is taken, wall clock (data fetch included) and CPU time of this process. The mean loss of the last five
steps of each is written beside (same batches, so they should be close). Records the CPU model, its bf16 flags
and the load average.
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

REPO = Path(__file__).resolve().parents[1]
RECIPES = {"fp32": [], "amp=bf16": ["amp=\"bf16\""]}


def main(argv=None) -> None:
    from ago_runtime.atomic import write_text
    from ago_runtime.providers import BF16_FLAGS, cpu_flags
    from benchmarks.bf16_openvino import FLAGS, cpu_model, uptime
    from benchmarks.train_step_speed import Batches, make_trainer

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--pseudo", required=True)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", default="/tmp/ago-amp-bf16")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "amp_bf16.md")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    os.environ.setdefault("AGO_NO_PROGRESS", "1")
    flags = cpu_flags()
    load0 = uptime()
    trainers = {name: make_trainer(ov, args.data, args.pseudo, Path(args.work) / f"r{i}")
                for i, (name, ov) in enumerate(RECIPES.items())}
    feeds = {name: Batches(t) for name, t in trainers.items()}
    step_s = {n: [] for n in trainers}
    cpu_s = {n: [] for n in trainers}
    losses = {n: [] for n in trainers}
    for i in range(args.warmup + args.steps):
        for name, t in trainers.items():
            c0 = time.process_time()
            batch, fetch = feeds[name].next()
            t0 = time.perf_counter()
            out = t.train_step(batch)
            dt = time.perf_counter() - t0
            losses[name].append(float(out["total"].detach()))
            if i >= args.warmup:
                step_s[name].append(dt + fetch)
                cpu_s[name].append(time.process_time() - c0)
    load1 = uptime()
    med = {n: statistics.median(v) for n, v in step_s.items()}
    cpu = {n: statistics.median(v) for n, v in cpu_s.items()}
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    cmd = "python -m benchmarks.amp_bf16 " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    lines = ["# Mixed precision in training: `--set amp=bf16` against float32 (issue 52 item 4)", "",
             f"Command: `{cmd}` (commit {commit}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; torch "
             f"{torch.__version__}, {args.threads} torch threads).", "",
             f"CPU: {cpu_model()}, {os.cpu_count()} cores; flags: {', '.join(f for f in FLAGS if f in flags)}"
             f" (bf16 units: {'yes' if set(BF16_FLAGS) & flags else 'no'}).",
             f"Recipe: `TrainConfig.preset(\"cpu\")` on {args.data} (its feature cache, 4000-voxel stratified sample), "
             f"{args.steps} timed steps each after {args.warmup} warm-up steps, alternating.",
             f"Load: before `{load0}`; after `{load1}`. **The machine was shared with other jobs: the figures are "
             "provisional** (a ratio of neighbours in time; the lead may re-run).", "",
             "| | fp32 | amp=bf16 |", "|---|---:|---:|",
             f"| median step (s, data included) | {med['fp32']:.3f} | {med['amp=bf16']:.3f} |",
             f"| speed-up over fp32 (wall clock) | 1.00x | {med['fp32'] / med['amp=bf16']:.2f}x |",
             f"| median CPU time of a step (s) | {cpu['fp32']:.3f} | {cpu['amp=bf16']:.3f} |",
             f"| speed-up over fp32 (CPU time) | 1.00x | {cpu['fp32'] / cpu['amp=bf16']:.2f}x |",
             f"| loss, mean of the last 5 steps (same batches) | {statistics.mean(losses['fp32'][-5:]):.3f} | "
             f"{statistics.mean(losses['amp=bf16'][-5:]):.3f} |", ""]
    text = "\n".join(lines)
    write_text(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
