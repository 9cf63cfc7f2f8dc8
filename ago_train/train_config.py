"""`TrainConfig`: everything one training run needs, as a dataclass that builds its own objects.

No registries: the config holds plain values plus the model's `ModelConfig` and the loss's
`LossConfig`; `Trainer(config)` builds the dataset, model, optimiser and schedule from it.
A config is saved as JSON (`save` / `load`) and changed from the command line with
`--set key=value` (dotted keys reach into `model.` and `loss.`; values are parsed as JSON when
they parse, else taken as strings: `--set epochs=3 --set model.embed_dim=64 --set out=runs/x`).

Presets (`TrainConfig.preset(name)`):
- "tiny": the test suite's; a few optimiser steps on a handful of synthetic frames (seconds).
- "cpu": a meaningful run on a 2-core CPU (the model's cpu preset, a small synthetic dataset, a few
  epochs); see docs/training.md for the commands (times: benchmarks/results/training_cpu.md).
- "full": the paper's schedule: AdamW lr 1e-3, weight decay 0.01, 500 warm-up steps from 1e-5,
  cosine to 1e-6, 24 epochs, batch 1 per GPU on 8 GPUs (total 8), 100 noise words per step.

Learning-rate schedule (per optimiser step): linear warm-up from `warmup_lr` to `lr` over
`warmup_steps`, then cosine from `lr` down to `min_lr` at the last step. When a run is short
the warm-up is capped at `warmup_max_fraction` of all steps (default 5 %; the paper's 500 steps
are ~0.6 % of its ~84k steps, so the cap only bites for small runs).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ago_runtime.atomic import write_json
from ago_runtime.errors import AgoInputError
from ago_runtime.readers import read_json
from ago_runtime.vocab.prompts import resolve_prompt_file

from .losses import LossConfig
from .model import ModelConfig

PRESETS = ("tiny", "cpu", "full")


@dataclass
class TrainConfig:
    """One training run. Paths are strings so the config is plain JSON."""

    name: str = "cpu"                 # preset it started from (for the record)
    # ---- data ----
    data: str = "data/synth-cpu"      # dataset root (nuScenes layout or `ago synth` output)
    gts: str | None = None            # Occ3D gts root when not <data>/gts
    pseudo: str = "data/synth-cpu-pseudo"  # pseudo-label dir made by `ago pseudo-labels`
    sources: list[dict] | None = None  # several [{data, pseudo, weight, split}] at once (sources.py); when set,
                                       # they replace data / pseudo / train_split
    prompts: str = "cw"               # prompt file (label space); a bare name means prompts/<name>.txt
    text_encoder: str | None = None   # a CLIP save_pretrained folder whose text tower makes the banks (None = MiniLM);
                                      # model.embed_dim follows its projection width (docs/prompts.md)
    train_split: str = "train"
    val_split: str = "val"
    max_frames: int | None = None     # use only the first N training frames (None = all)
    frame_tokens: list[str] | None = None  # train only on these sample tokens (few-shot subsets)
    color_jitter: float = 0.0         # augmentation: max relative brightness/contrast change (0 = off)
    augment: str = "none"             # grid symmetries (ago_train/augment.py): "none", "flip", "flip+rot180"
    # ---- model and loss ----
    model: ModelConfig = field(default_factory=lambda: ModelConfig.preset("cpu"))
    loss: LossConfig = field(default_factory=LossConfig)
    init_from: str | None = None      # checkpoint whose model weights start this run (fine-tuning)
    quant: str = "none"               # "int8": quantisation-aware fine-tuning of init_from's model (fake int8 on
                                      # the convolutions, distilled from init_from's fp32 model; ago_train/quant.py)
    train_voxels: int = 0             # voxel heads + losses on a sample of this many voxels per frame
                                      # (ago_train.losses.sampling; 0 = the whole grid)
    voxel_sampling: str = "stratified"  # "stratified" (occupied/free strata + importance weights) | "priority"
    occupied_share: float = 0.5       # share of the sample drawn from occupied voxels ("stratified"; the
                                      # weights restore the pseudo-labels' own proportions)
    item_memory_mb: int = 0           # keep up to this many MiB of training items in memory (files read once)
    feature_cache: str = "off"        # cache of the frozen backbone stages' maps (ago_train/feature_cache.py):
                                      # "off", "auto" (~/.cache/ago/features) or a folder
    # ---- optimisation ----
    epochs: int = 24
    max_steps: int | None = None      # stop after this many optimiser steps (None = epochs * steps/epoch)
    batch_size: int = 1               # per process
    lr: float = 1e-3
    backbone_lr_mult: float = 1.0     # the image backbone's learning rate = lr x this (TPVFormer: 0.1)
    fpn_lr_mult: float = 1.0          # the FPN's learning rate = lr x this
    weight_decay: float = 0.01
    warmup_lr: float = 1e-5
    warmup_steps: int = 500
    warmup_max_fraction: float = 0.05
    min_lr: float = 1e-6
    grad_clip: float = 35.0           # max gradient norm (0 = off)
    amp: str = "none"                 # mixed precision: "none" | "bf16" (the forward under torch.autocast in
                                      # bfloat16, the losses in float32; ago_train/amp.py)
    noise_words: int = 100            # noise-word prompts sampled per step (negatives)
    noise_bank: str | None = None     # .npz noise bank; None = the bundled/default one
    seed: int = 0
    # ---- bookkeeping ----
    out: str = "runs/train"
    log_every: int = 10               # steps between log lines (log.jsonl, rank 0)
    ckpt_every: int = 500             # steps between checkpoints (plus one at the end)
    snapshot_steps: list[int] | None = None  # also keep a model-only checkpoint <out>/snapshots/step_NNNNNN.pt
                                      # at these steps (learning curves: benchmarks/learning_curve.py)
    num_workers: int = 0
    device: str = "auto"              # auto | cpu | cuda

    # ---------------------------------------------------------------------------------------
    @classmethod
    def preset(cls, name: str) -> "TrainConfig":
        if name == "tiny":
            return cls(name="tiny", model=ModelConfig.preset("tiny"), epochs=1, max_steps=4, batch_size=1,
                       warmup_steps=2, log_every=1, ckpt_every=1000, noise_words=8, prompts="cw",
                       data="runs/synth-tiny", pseudo="runs/synth-tiny-pseudo", out="runs/train-tiny")
        if name == "cpu":
            # The recipe of docs/training.md ("The cpu recipe"): the whole ImageNet backbone frozen and its
            # maps cached, a stratified 4000-voxel sample with importance weights, mirror / half-turn
            # augmentation, 4000 steps (time on a 2-core CPU: benchmarks/results/training_cpu.md).
            model = ModelConfig.preset("cpu")
            model.frozen_stages = 3
            return cls(name="cpu", model=model, epochs=1000, max_steps=4000, batch_size=1, max_frames=None,
                       train_voxels=4000, voxel_sampling="stratified", occupied_share=0.5, feature_cache="auto",
                       item_memory_mb=3072, augment="flip+rot180",
                       warmup_steps=500, log_every=10, ckpt_every=250, noise_words=100,
                       prompts="cw", data="runs/synth-cpu", pseudo="runs/synth-cpu-pseudo", out="runs/train-cpu")
        if name == "full":
            # backbone and FPN at 0.1x the learning rate (as TPVFormer trains its backbone) and the free score's
            # prior-initialised bias (model.free_bias): without them the voxel features collapse to one vector
            # in ~10 steps and every voxel is free (docs/training.md, "Does it learn?")
            return cls(name="full", model=ModelConfig.preset("full"), epochs=24, batch_size=1, warmup_steps=500,
                       backbone_lr_mult=0.1, fpn_lr_mult=0.1,
                       log_every=50, ckpt_every=2000, noise_words=100, prompts="cw", num_workers=4,
                       data="data/nuscenes", pseudo="data/nuscenes-pseudo", out="runs/train-full")
        raise AgoInputError(None, f"unknown training preset {name!r}; choose one of {list(PRESETS)} or a .json file")

    # ---------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["model"] = self.model.to_dict()
        d["loss"] = dataclasses.asdict(self.loss) if dataclasses.is_dataclass(self.loss) else dict(self.loss)
        if d["frame_tokens"] is not None:
            d["frame_tokens"] = list(d["frame_tokens"])
        if d["sources"] is not None:
            d["sources"] = [dict(s) for s in d["sources"]]
        if d["snapshot_steps"] is not None:
            d["snapshot_steps"] = [int(s) for s in d["snapshot_steps"]]
        return d

    @classmethod
    def from_dict(cls, d: dict, source: str | None = None) -> "TrainConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise AgoInputError(source, f"unknown training config keys {unknown}")
        kw = dict(d)
        if "model" in kw and not isinstance(kw["model"], ModelConfig):
            if not isinstance(kw["model"], dict):
                raise AgoInputError(source, f"model must be an object of model settings, got {kw['model']!r}")
            kw["model"] = ModelConfig.from_dict(kw["model"], source)
        if "loss" in kw and not isinstance(kw["loss"], LossConfig):
            if not isinstance(kw["loss"], dict):
                raise AgoInputError(source, f"loss must be an object of loss settings, got {kw['loss']!r}")
            loss_fields = {f.name for f in dataclasses.fields(LossConfig)}
            bad = sorted(set(kw["loss"]) - loss_fields)
            if bad:
                raise AgoInputError(source, f"unknown loss config keys {bad}")
            try:
                kw["loss"] = LossConfig(**kw["loss"])
            except ValueError as e:
                raise AgoInputError(source, str(e)) from None
        from .config_checks import check_train_config

        return check_train_config(cls(**kw), source)

    def save(self, path: str | Path) -> None:
        write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> "TrainConfig":
        path = Path(path)
        d = read_json(path, missing="training config file not found")
        if not isinstance(d, dict):
            raise AgoInputError(path, "a training config must be a JSON object")
        return cls.from_dict(d, source=str(path))

    @classmethod
    def from_name_or_path(cls, spec: str) -> "TrainConfig":
        """A preset name ("tiny", "cpu", "full") or a path to a JSON config."""
        if spec in PRESETS:
            return cls.preset(spec)
        return cls.load(spec)

    def with_overrides(self, assignments: list[str] | None) -> "TrainConfig":
        """A copy with `key=value` assignments applied (dotted keys into model./loss.)."""
        d = self.to_dict()
        for a in assignments or []:
            if "=" not in a:
                raise AgoInputError(None, f"--set needs key=value, got {a!r}")
            key, raw = a.split("=", 1)
            if len(raw) > 100_000:
                raise AgoInputError("--set", f"{key.strip()}: value of {len(raw)} characters (at most 100000)")
            try:
                value: Any = json.loads(raw)
            except json.JSONDecodeError:
                value = raw
            except RecursionError:
                raise AgoInputError("--set", f"{key.strip()}: value nested too deeply") from None
            target = d
            parts = key.strip().split(".")
            for p in parts[:-1]:
                if not isinstance(target.get(p), dict):
                    raise AgoInputError(None, f"--set {key}: {p!r} is not a config section")
                target = target[p]
            if parts[-1] not in target:
                raise AgoInputError(None, f"--set {key}: no such config key")
            target[parts[-1]] = value
        return TrainConfig.from_dict(d, source="--set" if assignments else None)

    # ---------------------------------------------------------------------------------------
    def uses_feature_cache(self) -> bool:
        """True when training reads the frozen backbone maps from the cache instead of the images:
        `feature_cache` is not "off", the backbone has frozen stages and no colour jitter changes the images (nor
        fake int8, `quant`, the frozen stages' outputs)."""
        return (self.feature_cache not in ("off", "", None) and self.model.frozen_stages > 0
                and self.model.backbone != "tiny_cnn" and self.color_jitter == 0 and self.quant == "none")

    def prompt_path(self) -> Path:
        return resolve_prompt_file(self.prompts)

    def run_length(self, steps_per_epoch: int) -> tuple[int, str | None]:
        """(optimiser steps of the run, a `note:` line or None). The run stops at whichever of `epochs` x
        `steps_per_epoch` and `max_steps` comes first, and the schedule (warm-up, cosine) is sized to that
        length. The note says which limit wins when both are set and they disagree, so a run is never
        silently shorter (or longer) than the number a user typed."""
        by_epochs = self.epochs * steps_per_epoch
        if self.max_steps is None or self.max_steps == by_epochs:
            return by_epochs, None
        if by_epochs < self.max_steps:
            return by_epochs, (f"note: epochs={self.epochs} x {steps_per_epoch} steps per epoch = {by_epochs} steps "
                               f"comes before max_steps={self.max_steps}: the run and its learning-rate schedule "
                               f"are {by_epochs} steps (raise epochs, e.g. --set epochs="
                               f"{math.ceil(self.max_steps / max(steps_per_epoch, 1))}, to train {self.max_steps})")
        return self.max_steps, (f"note: max_steps={self.max_steps} comes before epochs={self.epochs} x "
                                f"{steps_per_epoch} steps per epoch = {by_epochs}: the run and its learning-rate "
                                f"schedule are {self.max_steps} steps "
                                f"({self.max_steps / max(steps_per_epoch, 1):.1f} epochs)")

    def effective_warmup(self, total_steps: int) -> int:
        """Warm-up steps actually used: `warmup_steps`, capped at `warmup_max_fraction` of the run."""
        cap = max(1, int(math.floor(self.warmup_max_fraction * max(total_steps, 1))))
        return max(0, min(self.warmup_steps, cap))

    def lr_at(self, step: int, total_steps: int) -> float:
        """Learning rate for optimiser step `step` (0-based) of `total_steps`."""
        warm = self.effective_warmup(total_steps)
        if step < warm:
            return self.warmup_lr + (self.lr - self.warmup_lr) * step / warm
        span = max(total_steps - warm - 1, 1)
        t = min(max(step - warm, 0) / span, 1.0)
        return self.min_lr + 0.5 * (self.lr - self.min_lr) * (1.0 + math.cos(math.pi * t))
