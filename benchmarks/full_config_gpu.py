"""The paper's full configuration on a GPU: does `TrainConfig.preset("full")` train (and evaluate) on CUDA?

    # here, on the CPU machine: the inputs the GPU machine cannot make (it has no MiniLM or WordNet files)
    python benchmarks/full_config_gpu.py prepare --work work/gpucheck
    # on a machine with a GPU (the lent H200 of this project: docs/training.md)
    python benchmarks/full_config_gpu.py run --work work/gpucheck --steps 40 --out full_config_gpu.md

prepare: a synthetic town of 2 scenes x 3 keyframes at 1600x900 with Occ3D 200x200x16 ground truth,
its closed-world pseudo-labels on the full grid (simulated segmenter and embedder: simulations), and
the cw text bank and the noise-word bank as files.

run: the `full` preset unchanged (1600x928 input, EfficientNet-Lite0 with stage 1 frozen and its
features cached, TPV 100x100x16 planes of width 128, 3 encoder layers, the whole 200x200x16 grid in
the heads and losses, 100 noise words per step) except `model.pretrained=false` (the ImageNet weights
change the numbers, not the cost) and `device=cuda`, trained `--steps` optimiser steps on the town's
train frames: the median step time, peak GPU memory and the loss at the start and end (a few frames
seen many times: it must fall). Then `ago eval` of the checkpoint on the val frames, on the GPU.
Writes a markdown file with the command.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def ago(*args: str) -> subprocess.CompletedProcess:
    r = subprocess.run([sys.executable, "-m", "ago_runtime.cli", *args], capture_output=True, text=True,
                       env={**os.environ, "AGO_NO_PROGRESS": "1"})
    print(f"$ ago {' '.join(args)} -> rc {r.returncode}", flush=True)
    return r


def prepare(work: Path) -> None:
    import torch

    from ago_runtime.vocab.prompts import parse_prompt_file
    from ago_train.text.noise import ensure_noise_bank
    from ago_train.trainer import build_text_bank

    work.mkdir(parents=True, exist_ok=True)
    if not (work / "synth" / "splits.json").is_file():
        r = ago("synth", "--out", str(work / "synth"), "--scenes", "2", "--frames", "3", "--seed", "7",
                "--image-size", "1600x900", "--grid", "200x200x16", "--val-fraction", "0.5")
        assert r.returncode == 0, r.stderr
    r = ago("pseudo-labels", "--data", str(work / "synth"), "--out", str(work / "pseudo"), "--prompts", "cw",
            "--grid", "200x200x16", "--split", "train", "--segmenter", "sim", "--embedder", "sim",
            "--keyframes", "3", "--interval", "1")
    assert r.returncode == 0, r.stderr
    torch.save(build_text_bank(parse_prompt_file("cw")), work / "cw_bank.pt")
    shutil.copyfile(ensure_noise_bank(), work / "noise_bank.npz")
    print(f"prepared {work}")


def run(work: Path, steps: int, out: Path, device: str = "cuda", extra: list[str] | None = None,
        eval_split: str = "val") -> None:
    import torch

    import ago_train.trainer as trainer_module
    from ago_train.dataset import collate
    from ago_train.train_config import TrainConfig

    cuda = device.startswith("cuda")
    assert torch.cuda.is_available() or not cuda, "no CUDA device"
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    bank = torch.load(work / "cw_bank.pt", weights_only=True)
    trainer_module.build_text_bank = lambda space: {k: (v.clone() if torch.is_tensor(v) else v)
                                                    for k, v in bank.items()}
    run_dir = work / "train-full"
    shutil.rmtree(run_dir, ignore_errors=True)
    cfg = TrainConfig.preset("full").with_overrides(
        [f"data=\"{work / 'synth'}\"", f"pseudo=\"{work / 'pseudo'}\"", f"out=\"{run_dir}\"",
         f"noise_bank=\"{work / 'noise_bank.npz'}\"", "model.pretrained=false", f"device=\"{device}\"",
         f"max_steps={steps + 2}", "log_every=1000", "ckpt_every=100000", "num_workers=0", *(extra or [])])
    t = trainer_module.Trainer(cfg, quiet=True)
    t0 = time.perf_counter()
    t.setup()
    setup_s = time.perf_counter() - t0
    t.ddp.train()
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    times, losses, epoch = [], [], 0
    while len(times) < steps:
        t.sampler.set_epoch(epoch)
        for batch in torch.utils.data.DataLoader(t.dataset, batch_size=1, sampler=list(t.sampler),
                                                 collate_fn=collate):
            if len(times) >= steps:
                break
            sync()
            s0 = time.perf_counter()
            o = t.train_step(batch)
            sync()
            times.append(time.perf_counter() - s0)
            losses.append(float(o["total"].detach()))
        epoch += 1
    peak = torch.cuda.max_memory_allocated() / 2**30 if cuda else float("nan")
    result = t.run()     # the last 2 steps through the trainer's own loop: writes last.pt
    ev = ago("eval", "--ckpt", str(result["last"]), "--data", str(work / "synth"), "--split", eval_split,
             "--out", str(work / "eval"), "--device", device) if Path(result["last"]).is_file() else None
    eval_line = "not run (no checkpoint)"
    if ev is not None and ev.returncode == 0:
        m = json.loads((work / "eval" / "metrics.json").read_text()) if (work / "eval" / "metrics.json").is_file() else {}
        eval_line = f"ran on {device} (rc 0); {eval_split} split: mIoU {m.get('mIoU')}, geometry IoU {m.get('geometry_IoU')} " \
                    f"(3 training frames: a check that it fits, not a score)"
    elif ev is not None:
        eval_line = f"failed (rc {ev.returncode}): {(ev.stderr or ev.stdout).strip()[-300:]}"
    med = statistics.median(times[2:]) if len(times) > 4 else statistics.median(times)
    L = ["# The paper's full configuration on a GPU", "",
         f"Command: `python benchmarks/full_config_gpu.py run --work {work} --steps {steps} --eval-split {eval_split} "
         f"--out {out.name}` "
         f"(inputs from `... prepare`), {time.strftime('%Y-%m-%d')}, on "
         f"{torch.cuda.get_device_name() if cuda else 'the CPU'} "
         f"(torch {torch.__version__}).", "",
         f"`TrainConfig.preset(\"full\")` with `model.pretrained=false`, `device={device}` {extra or ''} on a 2-scene synthetic "
         "town at 1600x900 (3 train frames, cw pseudo-labels on the 200x200x16 grid: simulations).", "",
         "| what | value |", "|---|---|",
         f"| trainer setup (dataset, bank, model, feature cache fill) | {setup_s:.1f} s |",
         f"| optimiser steps timed | {len(times)} |",
         f"| median step (steps 3..{len(times)}) | {med * 1000:.0f} ms |",
         f"| first step | {times[0] * 1000:.0f} ms |",
         f"| peak GPU memory (torch allocator) | {peak:.2f} GiB |",
         f"| loss, mean of the first 3 steps -> last 3 | {statistics.mean(losses[:3]):.3f} -> "
         f"{statistics.mean(losses[-3:]):.3f} |",
         f"| loss finite at every step | {all(map(lambda x: x == x and abs(x) != float('inf'), losses))} |",
         f"| `ago eval --device {device} --split {eval_split}` of the checkpoint | {eval_line} |", "",
         "Losses per step: " + ", ".join(f"{x:.3f}" for x in losses), ""]
    out.write_text("\n".join(L))
    print("\n".join(L))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("mode", choices=["prepare", "run"])
    ap.add_argument("--work", type=Path, default=Path("work/gpucheck"))
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--out", type=Path, default=Path("full_config_gpu.md"))
    ap.add_argument("--eval-split", default="val", help="split `ago eval` scores (train: did it fit its frames)")
    ap.add_argument("--device", default="cuda", help="cuda (the check) | cpu (a smoke test of this script)")
    ap.add_argument("--set", action="append", default=[], help="extra TrainConfig override (smoke tests only)")
    a = ap.parse_args()
    prepare(a.work) if a.mode == "prepare" else run(a.work, a.steps, a.out, a.device, a.set, a.eval_split)


if __name__ == "__main__":
    main()
