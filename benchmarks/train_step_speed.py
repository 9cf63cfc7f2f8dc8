"""Training-step cost of the `cpu` preset: today's recipe vs the new one, in one run, split by part.

    python -m benchmarks.train_step_speed --data DIR --pseudo DIR [--steps 20] [--warmup 3] \
        [--out benchmarks/results/train_step_speed.md]

Three `Trainer`s are built on the same frames and pseudo-labels:
- "before": the cpu preset as it was at commit 073a3f4 (images decoded and the whole backbone run at
  every step, the 8000-voxel priority sample: `feature_cache=off`, `voxel_sampling=priority`, the
  TPV encoder's reference arithmetic, torch's default AdamW);
- "after, reference TPV + unfused AdamW": today's recipe without the canvas TPV layout and the fused
  optimiser (what the two buy on their own);
- "after": the cpu preset of today (`TrainConfig.preset("cpu")` with the same data).
Their steps are interleaved (before, ..., after, before, ...) so that the load of the machine weighs on
both alike, and the median of each is taken over `--steps` steps after `--warmup` steps.

Every timed step is `Trainer.train_step` itself (data fetch timed apart). The split by part comes
from extra profiled steps that run the same computation piece by piece, with perf_counter around each
forward part and gradient hooks on the boundary tensors for the backward parts: data, backbone
(frozen stages), backbone (trained stages), FPN, TPV encoder, voxel heads, losses, and the backward
of heads/TPV/FPN/backbone, plus the optimiser. Writes a markdown table to `--out`.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]

from ago_runtime.atomic import write_text  # noqa: E402
from ago_train.losses import BankTensors, compute_losses  # noqa: E402
from ago_train.model.aggregate import planes_at_voxels, planes_to_voxels  # noqa: E402
from ago_train.train_config import TrainConfig  # noqa: E402
from ago_train.trainer import Trainer, _to_device  # noqa: E402

BEFORE = ["feature_cache=\"off\"", "voxel_sampling=\"priority\"", "train_voxels=8000", "model.frozen_stages=1",
          "model.tpv_layout=\"reference\""]
# the same recipe as "after" with the TPV encoder's reference arithmetic and the unfused AdamW: what the
# canvas layout (ago_train/model/tpv_canvas.py) and the fused optimiser buy on their own
REFERENCE_TPV = ["model.tpv_layout=\"reference\""]
RECIPES = {"before": BEFORE, "after, reference TPV + unfused AdamW": REFERENCE_TPV, "after": []}


def make_trainer(overrides: list[str], data: str, pseudo: str, out: Path, fused_adamw: bool = True) -> Trainer:
    cfg = TrainConfig.preset("cpu").with_overrides(
        [f"data=\"{data}\"", f"pseudo=\"{pseudo}\"", f"out=\"{out}\"", "max_steps=100000", "log_every=100000",
         "ckpt_every=100000", *overrides])
    t = Trainer(cfg, quiet=True)
    t.setup()
    if not fused_adamw:   # the optimiser of the earlier recipes (torch's default foreach AdamW)
        params = [p for p in t.model.parameters() if p.requires_grad]
        t.optimizer = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay, fused=False)
        t.scheduler = torch.optim.lr_scheduler.LambdaLR(t.optimizer, lambda s: cfg.lr_at(s, t.total_steps) / cfg.lr)
    t.ddp.train()
    return t


class Batches:
    """Endless batches of a trainer's dataset in its sampler's order; times each fetch."""

    def __init__(self, trainer: Trainer):
        self.t = trainer
        self.epoch = 0
        self._it = None

    def next(self) -> tuple[dict, float]:
        t0 = time.perf_counter()
        while True:
            if self._it is None:
                self.t.sampler.set_epoch(self.epoch)
                loader = torch.utils.data.DataLoader(self.t.dataset, batch_size=1, sampler=list(self.t.sampler),
                                                     collate_fn=__import__("ago_train.dataset", fromlist=["collate"]).collate)
                self._it = iter(loader)
            try:
                batch = next(self._it)
                return batch, time.perf_counter() - t0
            except StopIteration:
                self._it = None
                self.epoch += 1


def profiled_step(t: Trainer, batch: dict) -> dict[str, float]:
    """The computation of Trainer.train_step piece by piece, timed (seconds per part)."""
    model, cfg = t.model, t.cfg
    times: dict[str, float] = {}
    batch = _to_device(batch, t.info.device)
    clock = time.perf_counter

    def part(name, fn):
        t0 = clock()
        r = fn()
        times[name] = times.get(name, 0.0) + clock() - t0
        return r

    if "prefix" in batch:
        prefix = part("backbone, frozen stages (cache read)", lambda: [p.reshape(-1, *p.shape[2:]).float()
                                                                        for p in batch["prefix"]])
    else:
        with torch.no_grad():
            prefix = part("backbone, frozen stages", lambda: model.frozen_prefix(batch["images"]))
    maps = part("backbone, trained stages", lambda: model.backbone.from_prefix(prefix))
    feats = part("FPN", lambda: model.fpn(maps))
    planes = part("TPV encoder", lambda: model.encoder(feats, batch["ego2img"]))
    vi, vw = t.voxels_for_step(batch, t.step)

    def heads():
        vox = planes_to_voxels(planes, model.grid_shape) if vi is None else \
            planes_at_voxels(planes, model.grid_shape, vi)
        h = model.decoder(vox)
        feat = model.decoder_out(h)
        out = {"feat": feat, "free_embedding": model.free_embedding}   # F~_3D: in the losses, align rows only
        if vi is not None:
            out["voxel_index"] = vi
        return vox, out

    vox, outputs = part("voxel heads", heads)
    bank = BankTensors(t.text, t.phrase_class, t.label_space.num_classes, t.noise_for_step(t.step))
    losses = part("losses", lambda: compute_losses(outputs, batch, bank, cfg.loss, sample_weight=vw,
                                                   adapter=model.adapt))
    marks: dict[str, float] = {}

    def mark(name):
        def hook(grad):
            marks.setdefault(name, clock())
            return grad
        return hook

    vox.register_hook(mark("heads"))
    for f in feats:
        f.register_hook(mark("tpv"))
    for m in maps:
        if m.requires_grad:
            m.register_hook(mark("fpn"))
    t.optimizer.zero_grad(set_to_none=True)
    t0 = clock()
    losses["total"].backward()
    t_end = clock()
    heads_done = marks.get("heads", t_end)
    tpv_done = marks.get("tpv", heads_done)
    fpn_done = marks.get("fpn", tpv_done) if any(m.requires_grad for m in maps) else t_end
    times["backward: heads + losses"] = heads_done - t0
    times["backward: TPV encoder"] = tpv_done - heads_done
    times["backward: FPN"] = fpn_done - tpv_done
    times["backward: backbone"] = t_end - fpn_done
    t1 = clock()
    if cfg.grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
    t.optimizer.step()
    times["optimiser"] = clock() - t1
    t.optimizer.zero_grad(set_to_none=True)
    return times


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--pseudo", required=True)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--profiled", type=int, default=5, help="profiled steps per recipe for the split")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/train_step_speed.md"))
    ap.add_argument("--work", default="/tmp/ago-train-step-speed")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    os.environ.setdefault("AGO_NO_PROGRESS", "1")
    work = Path(args.work)
    trainers = {name: make_trainer(ov, args.data, args.pseudo, work / f"r{i}", fused_adamw=(name == "after"))
                for i, (name, ov) in enumerate(RECIPES.items())}
    feeds = {name: Batches(t) for name, t in trainers.items()}
    load0 = os.getloadavg()
    step_s = {n: [] for n in trainers}
    cpu_s = {n: [] for n in trainers}
    data_s = {n: [] for n in trainers}
    for i in range(args.warmup + args.steps):
        for name, t in trainers.items():
            c0 = time.process_time()
            batch, fetch = feeds[name].next()
            t0 = time.perf_counter()
            t.train_step(batch)
            dt = time.perf_counter() - t0
            if i >= args.warmup:
                step_s[name].append(dt + fetch)
                cpu_s[name].append(time.process_time() - c0)
                data_s[name].append(fetch)
    split = {n: [] for n in trainers}
    for _ in range(args.profiled):
        for name, t in trainers.items():
            batch, fetch = feeds[name].next()
            parts = profiled_step(t, batch)
            parts = {"data (fetch + collate)": fetch, **parts}
            split[name].append(parts)
            t.step += 1
    load1 = os.getloadavg()
    med = {n: statistics.median(v) for n, v in step_s.items()}
    cpu = {n: statistics.median(v) for n, v in cpu_s.items()}
    ratio = med["before"] / med["after"]
    cpu_ratio = cpu["before"] / cpu["after"]
    order = list(trainers)
    names = []
    for n in order:
        names += [k for k in split[n][0] if k not in names]
    rows = []
    for k in names:
        vals = [statistics.median(p.get(k, 0.0) for p in split[n]) * 1000 for n in order]
        rows.append(f"| {k} | " + " | ".join(f"{v:.0f}" for v in vals) + " |")
    tot = [sum(statistics.median(p.get(k, 0.0) for p in split[n]) for k in names) * 1000 for n in order]
    head = " | ".join(order)
    line = lambda label, vals: f"| {label} | " + " | ".join(vals) + " |"   # noqa: E731
    cmd = "python -m benchmarks.train_step_speed " + " ".join(argv if argv is not None else sys.argv[1:])
    cfg_after = trainers["after"].cfg
    text = f"""# Training step of the `cpu` preset: before vs after (one run, interleaved)

Command: `{cmd}`

- before: {', '.join(BEFORE)}, torch's default (foreach) AdamW (the cpu preset as at commit 073a3f4)
- after: `TrainConfig.preset("cpu")`: feature_cache={cfg_after.feature_cache}, voxel_sampling={cfg_after.voxel_sampling},
  train_voxels={cfg_after.train_voxels}, frozen_stages={cfg_after.model.frozen_stages},
  tpv_layout={cfg_after.model.tpv_layout}, fused AdamW
- after, reference TPV + unfused AdamW: the same with {', '.join(REFERENCE_TPV)} and the foreach AdamW
  (the recipe of the previous measurement)
- {args.steps} timed steps each after {args.warmup} warm-up steps, interleaved; torch threads {args.threads};
  load average {load0[0]:.2f} before, {load1[0]:.2f} after
- frames: {len(trainers['after'].dataset)} training frames of `{args.data}`

| | {head} |
|---|{"---:|" * len(order)}
{line("**median step (s), data included**", [f"**{med[n]:.3f}**" for n in order])}
{line("median data fetch (s)", [f"{statistics.median(data_s[n]):.3f}" for n in order])}
{line("**speed-up over before (wall clock)**", [f"**{med['before'] / med[n]:.2f}x**" for n in order])}
{line("median CPU time of a step (s, all threads of this process)", [f"{cpu[n]:.3f}" for n in order])}
{line("speed-up over before (CPU time: the work itself, less sensitive to other jobs)", [f"{cpu['before'] / cpu[n]:.2f}x" for n in order])}

## Split of a step by part (median ms over {args.profiled} profiled steps)

| part | {head} |
|---|{"---:|" * len(order)}
{chr(10).join(rows)}
{line("sum of parts", [f"{v:.0f}" for v in tot])}

Backward parts are read from gradient hooks on the boundary tensors (voxel features, FPN outputs,
backbone outputs), so each is the time between two boundaries of the one backward pass.
"""
    write_text(args.out, text)
    print(text)
    return {"before": med["before"], "after": med["after"], "ratio": ratio, "cpu_ratio": cpu_ratio}


if __name__ == "__main__":
    main()
