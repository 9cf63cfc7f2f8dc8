"""The training loop: single process or DDP (torchrun), resumable exactly from its checkpoints.

`Trainer(config).run()` builds, from the `TrainConfig`:
- the label space (prompt file) and its text bank, encoded once by the frozen MiniLM (no gradients);
- the noise-word bank (negatives; `noise_words` rows sampled per step by a generator seeded with
  (seed, step), so a resumed run draws the same words);
- the dataset (frames + pseudo-labels + E_3D) with a DistributedSampler (seeded; one rank = the whole
  set when single-process); the model (`ModelConfig.build()`), AdamW and a LambdaLR schedule
  (TrainConfig.lr_at: linear warm-up, cosine decay).

Every `ckpt_every` steps and at the end, rank 0 writes `<out>/last.pt` (see checkpoint.py) and a
line per `log_every` steps goes to `<out>/log.jsonl`. `resume=True` reloads `<out>/last.pt` —
model, optimiser, scheduler, step and RNG states — and skips the batches of the current epoch that
were already done, so N straight steps == N/2 steps + resume + N/2 steps.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader, DistributedSampler

from ago_runtime.atomic import write_text
from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.preprocess import Preprocess
from ago_runtime.vocab.prompts import LabelSpace, parse_prompt_file

from . import distributed as D
from .checkpoint import (BankRecord, CalibrationRecord, CheckpointContract, LabelSpaceRecord, TrainingState, plain,
                         rng_state, set_rng_state)
from .dataset import FrameList, OccSampleDataset, collate
from .quant import load_model_state, model_state
from .sources import open_sources
from .train_config import TrainConfig


# ---- pieces shared with evaluation --------------------------------------------------------------
_BANKS: dict[str, dict] = {}  # per process: prompt file sha256 -> bank dict (the encoder is frozen)


def build_text_bank(label_space: LabelSpace, text_encoder: str | None = None) -> BankRecord:
    """The label space's bank from the frozen torch MiniLM, or the text tower of the CLIP folder `text_encoder`
    (ago_train.text.clip), through ago_runtime.vocab.load_prompt_bank (cached by content hash) -> the checkpoint's
    BankRecord (a fresh copy of its tensors)."""
    from ago_runtime.vocab.bank import load_prompt_bank

    key = (label_space.sha256 or "\n".join(label_space.phrases)) + f"|{text_encoder}"
    if key not in _BANKS:
        if text_encoder is not None:
            from .text.clip import TorchClipTextEncoder

            encoder = TorchClipTextEncoder(text_encoder, "text_encoder")
        else:
            from .text.minilm import TorchMiniLMEncoder

            encoder = TorchMiniLMEncoder()
        _BANKS[key] = BankRecord.of_bank(load_prompt_bank(label_space, encoder))
    b = _BANKS[key]
    return dataclasses.replace(b, embeddings=b.embeddings.clone(), phrase_class=b.phrase_class.clone())


class TrainStep(nn.Module):
    """The model plus its losses in one module, so DDP sees every parameter used inside forward."""

    def __init__(self, model: nn.Module, loss_cfg, num_classes: int, amp: str = "none"):
        super().__init__()
        self.model = model
        self.loss_cfg = loss_cfg
        self.num_classes = int(num_classes)
        self.amp = amp          # "bf16": the model's forward under autocast, the losses in float32 (ago_train/amp.py)

    def forward(self, batch: dict, text: torch.Tensor, phrase_class: torch.Tensor,
                noise: torch.Tensor | None, voxel_index: torch.Tensor | None = None,
                voxel_weight: torch.Tensor | None = None, class_weight: torch.Tensor | None = None,
                diagnose: bool = False) -> dict:
        """The loss parts; with `diagnose`, also "feat_spread" and "free_share" of the voxels the losses
        saw (ago_train/fit_diagnostics.py; no gradients)."""
        from .amp import forward_autocast, outputs_to_float
        from .losses import BankTensors, compute_losses

        prefix = None
        if "prefix" in batch:  # cached frozen backbone maps (B, V, C, H, W) float16 -> (B*V, C, H, W) float32
            prefix = [p.reshape(-1, *p.shape[2:]).float() for p in batch["prefix"]]
        # F~_3D only where the alignment loss reads it (compute_losses runs the adapter on those rows)
        with forward_autocast(self.amp, batch["ego2img"].device.type):
            outputs = self.model(batch.get("images"), batch["ego2img"], voxel_index, prefix, adapted=False)
        outputs = outputs_to_float(outputs)
        bank = BankTensors(text, phrase_class, self.num_classes, noise)
        losses = compute_losses(outputs, batch, bank, self.loss_cfg, sample_weight=voxel_weight,
                                adapter=self.model.adapt, class_weight=class_weight)
        if diagnose:
            from .fit_diagnostics import feature_spread, free_share
            from .model.text_logits import class_logits

            with torch.no_grad():
                logits = class_logits(outputs["feat"], text, phrase_class, self.num_classes,
                                      outputs["free_embedding"], free_bias=outputs.get("free_bias"))
            losses["feat_spread"] = torch.tensor(feature_spread(outputs["feat"]))
            losses["free_share"] = torch.tensor(free_share(logits, self.num_classes))
        return losses


def parameter_groups(model: nn.Module, cfg: TrainConfig) -> list[dict]:
    """AdamW parameter groups: the image backbone at `backbone_lr_mult` x the learning rate, the FPN at
    `fpn_lr_mult` x, everything else at 1x (TPVFormer trains its image backbone at 0.1x). Each group's
    rate follows the same schedule (LambdaLR scales every group's initial rate). Frozen parameters and
    empty groups are left out; with both multipliers at 1 there is one group (as in runs made before the
    multipliers existed, so their checkpoints resume)."""
    if cfg.backbone_lr_mult == 1.0 and cfg.fpn_lr_mult == 1.0:
        return [{"params": [p for p in model.parameters() if p.requires_grad], "lr": cfg.lr, "name": "all"}]
    groups = {"backbone": [], "fpn": [], "rest": []}
    for name, param in model.named_parameters():
        if param.requires_grad:
            groups[name.split(".")[0] if name.split(".")[0] in ("backbone", "fpn") else "rest"].append(param)
    mult = {"backbone": cfg.backbone_lr_mult, "fpn": cfg.fpn_lr_mult, "rest": 1.0}
    return [{"params": ps, "lr": cfg.lr * mult[k], "name": k} for k, ps in groups.items() if ps]


def loader_workers(requested: int) -> int:
    """DataLoader worker processes for `num_workers` = `requested`: at most the cores this process may run on
    (its CPU affinity, else the CPU count), which is torch's own suggested maximum: the `full` preset's 4 become
    2 on a 2-core machine, with no warning from the DataLoader, and stay 4 where there are 4 or more."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:   # no affinity call on this OS (macOS, Windows)
        cores = os.cpu_count() or 1
    return max(0, min(int(requested), cores))


def _to_device(batch: dict, device: torch.device) -> dict:
    return {k: (v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v) for k, v in batch.items()}


class _Resumable(torch.utils.data.Sampler):
    """The indices a DistributedSampler gives for one epoch, minus the first `skip` of them."""

    def __init__(self, indices: list[int]):
        self.indices = indices

    def __iter__(self):
        return iter(self.indices)

    def __len__(self) -> int:
        return len(self.indices)


# ---- the trainer ------------------------------------------------------------------------------
class Trainer:
    def __init__(self, cfg: TrainConfig, resume: bool = False, dist_info: D.DistInfo | None = None,
                 quiet: bool = False):
        self.cfg = cfg
        self.resume = resume
        self.quiet = quiet
        self.info = dist_info
        self.out = Path(cfg.out)

    # -------------------------------------------------------------------------------------------
    def setup(self) -> None:
        cfg = self.cfg
        if self.info is None:
            self.info = D.setup(cfg.device)
        info = self.info
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed % (2 ** 32))
        import random

        random.seed(cfg.seed)

        self.prompt_path = cfg.prompt_path()
        self.label_space = parse_prompt_file(self.prompt_path)
        K = self.label_space.num_classes
        self.grid = cfg.model.grid_obj()
        use_cache = cfg.uses_feature_cache()
        # one or several (data, pseudo-labels) sources, checked against the grid, label space and each
        # other's rig before any work (sources.py)
        frames, self.pseudo, first_rig = open_sources(cfg, self.grid, self.label_space, load_images=not use_cache)
        init = CheckpointContract.load(cfg.init_from) if cfg.init_from else None   # checked before any work
        # the rig comes from the data: the model takes as many cameras as the training frames have
        if len(first_rig.cameras) != cfg.model.num_cameras:
            print(f"note: the training data's rig has {len(first_rig.cameras)} camera(s) ({', '.join(first_rig.names)}); "
                  f"model.num_cameras {cfg.model.num_cameras} -> {len(first_rig.cameras)}", file=sys.stderr, flush=True)
            cfg = self.cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model,
                                                                                num_cameras=len(first_rig.cameras)))
        self.preprocess = Preprocess(cfg.model.image_width, cfg.model.image_height)
        self.dataset = OccSampleDataset(frames, self.pseudo, K, self.grid, self.preprocess,
                                        with_embeds=True, color_jitter=cfg.color_jitter, seed=cfg.seed,
                                        memory_bytes=cfg.item_memory_mb << 20, augment=cfg.augment,
                                        camera_names=first_rig.names)
        # the camera rig of the training data (native image size), for export (a typical rig to trace with)
        self.rig = first_rig
        self.sampler = DistributedSampler(self.dataset, num_replicas=info.world_size, rank=info.rank,
                                          shuffle=True, seed=cfg.seed, drop_last=False)
        self.steps_per_epoch = math.ceil(len(self.sampler) / cfg.batch_size)
        self.total_steps, note = cfg.run_length(self.steps_per_epoch)   # printed once the inputs are checked

        # frozen text side: the label-space bank (encoded once) and the noise-word bank
        self.bank = build_text_bank(self.label_space, cfg.text_encoder)
        width = self.bank.dim
        if width != cfg.model.embed_dim and cfg.text_encoder is not None:   # the CLIP folder sets the width
            note = (f"note: the text encoder {self.bank.encoder_id} gives {width}-d embeddings; model.embed_dim "
                    f"{cfg.model.embed_dim} -> {width}" + (f"\n{note}" if note else ""))
            cfg = self.cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, embed_dim=width))
        if width != cfg.model.embed_dim:
            raise AgoInputError(self.prompt_path, f"text embeddings are {width}-d but "
                                f"the model's embed_dim is {cfg.model.embed_dim}")
        from .text.noise import training_noise_bank

        self.noise_bank = training_noise_bank(cfg.noise_bank, cfg.text_encoder, self.bank.encoder_id, self.bank.dim)

        # model, optimiser, schedule; seeded right here so nothing built before (the text encoder
        # draws random initial weights before loading its own) changes the model's initial weights
        torch.manual_seed(cfg.seed)
        self.model = cfg.model.build().to(info.device)
        self.model.train()  # the backbone's BatchNorm layers stay in eval mode (backbone._FrozenBNMixin)
        if init is not None:
            init.check_same_encoder(cfg.init_from, self.bank)
            init.load_weights(self.model, cfg.init_from, cfg.model, what="this run's model (init_from)")
        if self.model.free_bias is not None and not cfg.init_from:   # a resumed run loads its own below
            with torch.no_grad():
                self.model.free_bias.fill_(self._free_prior_logit())
        if use_cache:  # after init_from: the cache is keyed by the frozen weights the run really uses
            self.dataset.feature_cache = self._feature_cache()
        if cfg.quant == "int8":   # quantisation-aware fine-tuning, distilled from init_from's fp32 model (quant.py)
            from .quant import DistillStep, attach_fake_quant

            self.calibration = init.calibration   # the teacher's, in every checkpoint: the run reproduces it

            teacher = cfg.model.build(load_weights=False).to(info.device)
            init.load_weights(teacher, cfg.init_from, cfg.model, what="the teacher (init_from)")
            attach_fake_quant(self.model)
            self.step_module = DistillStep(self.model, teacher, K).to(info.device)
        else:
            self.step_module = TrainStep(self.model, cfg.loss, K, cfg.amp).to(info.device)
        # fused AdamW: the same update, one kernel per group of tensors
        fused = torch.device(info.device).type in ("cpu", "cuda")
        self.optimizer = torch.optim.AdamW(parameter_groups(self.model, cfg), lr=cfg.lr,
                                           weight_decay=cfg.weight_decay, fused=fused)
        total_steps = self.total_steps
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, lambda s: cfg.lr_at(s, total_steps) / cfg.lr)
        self.step = 0
        if self.resume:
            self._load_resume()
        # after the resume / init_from checks (a checkpoint of another encoder is named first): the voxel
        # embeddings the adapter aligns with must be in the bank's space
        from .pseudo.backends import check_features_fit_bank

        for pseudo in self.pseudo.sets:   # each source's pseudo-label folder
            if pseudo.has_embeds:
                emb = pseudo.meta["embedder"]
                check_features_fit_bank(f"the pseudo-labels' voxel embeddings ({emb.get('name')})",
                                        emb.get("encoder_id"), emb.get("channels"), "the text bank",
                                        self.bank.encoder_id, self.bank.dim,
                                        pseudo.root / "meta.json")
        if note and info.is_main and not self.quiet:   # after init_from / resume checks: an error stays one line
            print(note, file=sys.stderr, flush=True)
        if info.distributed:
            self.ddp = torch.nn.parallel.DistributedDataParallel(
                self.step_module, device_ids=[info.device.index] if info.device.type == "cuda" else None,
                # only the paper's "ago" variant uses every parameter (the others leave the adapter or
                # the free embedding out of the loss)
                find_unused_parameters=getattr(cfg.loss, "variant", "ago") != "ago")
        else:
            self.ddp = self.step_module
        self.text = self.bank.embeddings.to(info.device)
        self.phrase_class = self.bank.phrase_class.to(info.device)
        self.align_center = self._align_center() if cfg.loss.align_center and cfg.loss.uses_align else None
        self.class_weight = self._class_weight() if cfg.loss.class_balance > 0 and cfg.loss.uses_grounding else None

    def _class_weight(self) -> torch.Tensor:
        """(K + 1,) CE weights from the class counts of the training frames' pseudo-labels (training data
        only; losses/class_balance.py); the counts and weights are written to <out>/class_weights.json."""
        from .losses.class_balance import class_balance_weights, count_classes

        frames = self.dataset.frames
        labels = (self.pseudo.labels(frames[i].scene, frames[i].token) for i in range(len(frames)))
        K = self.label_space.num_classes
        counts = count_classes(labels, K)
        weights = class_balance_weights(counts, float(self.cfg.loss.class_balance))
        if self.info.is_main:
            self.out.mkdir(parents=True, exist_ok=True)
            names = list(self.label_space.class_names) + ["free"]
            write_text(self.out / "class_weights.json", json.dumps(
                {"class_balance": float(self.cfg.loss.class_balance), "frames": len(frames),
                 "classes": {n: {"voxels": int(c), "weight": round(float(w), 4)}
                             for n, c, w in zip(names, counts, weights)}}, indent=1) + "\n")
        return torch.as_tensor(weights, device=self.info.device)

    def _free_prior_logit(self) -> float:
        """The free score's starting bias: the prior log-odds of free among the labelled voxels of the training
        frames' pseudo-labels, plus log(K + noise words) so that with every other score ~0 the softmax gives
        free its prior probability. The model then starts at the loss of the class prior instead of
        reaching it by moving every voxel's embedding towards the free embedding (a common shift that
        erases their differences: docs/training.md, "Does it learn?")."""
        from .losses.class_balance import count_classes

        frames = self.dataset.frames
        K = self.label_space.num_classes
        counts = count_classes((self.pseudo.labels(frames[i].scene, frames[i].token) for i in range(len(frames))), K)
        free, occupied = float(counts[K]), float(counts[:K].sum())
        if free == 0 or occupied == 0:
            return 0.0
        noise = self.cfg.noise_words if getattr(self.cfg.loss, "use_noise", True) else 0
        return float(np.log(free / occupied) + np.log(K + noise))

    def _align_center(self) -> torch.Tensor:
        """(C,) mean E_3D over every aligned voxel of the training frames (training data only)."""
        total, count = None, 0
        for i in range(len(self.dataset.frames)):
            f = self.dataset.frames[i]
            _, emb = self.pseudo.embeds(f.scene, f.token)
            if emb.size:
                s = emb.astype(np.float64).sum(0)
                total = s if total is None else total + s
                count += len(emb)
        if count == 0:
            raise AgoInputError(self.cfg.pseudo, "align_center needs voxel embeddings (embeds.npz) in the pseudo-labels")
        return torch.as_tensor(total / count, dtype=torch.float32, device=self.info.device)

    def _feature_cache(self):
        """The frozen-prefix cache (feature_cache.py), filled for every training frame by rank 0."""
        from .feature_cache import FeatureCache

        root = None if self.cfg.feature_cache == "auto" else self.cfg.feature_cache
        cache = FeatureCache(self.model, self.preprocess, root)
        if self.info.is_main and not self.quiet:
            print(f"note: using feature cache {cache.dir} (frozen backbone maps of the training frames; "
                  "--set feature_cache=DIR moves it, $AGO_CACHE_DIR too)", file=sys.stderr, flush=True)
        if self.info.is_main:
            flips = (False, True) if self.cfg.augment != "none" else (False,)
            frames = self.dataset.frames   # each distinct frame once (a source's weight repeats frames)
            cache.fill(FrameList(frames, frames.unique()), progress=not self.quiet, flips=flips)
        D.barrier(self.info)
        return cache

    def _load_resume(self) -> None:
        path = self.out / "last.pt"
        ckpt = CheckpointContract.load(path, map_location=self.info.device)
        ckpt.check_resume(path, self.cfg, self.info.world_size, self.bank)
        load_model_state(self.model, ckpt.model)   # with fake int8 attached too (quant.py)
        self.optimizer.load_state_dict(ckpt.training.optimizer)
        self.scheduler.load_state_dict(ckpt.training.scheduler)
        self.step = ckpt.step
        set_rng_state(ckpt.training.rng_of_rank(self.info.rank))

    # -------------------------------------------------------------------------------------------
    def checkpoint_contract(self, epoch: int) -> CheckpointContract:
        """This step's checkpoint (collective in DDP: every rank's RNG state, so a resumed run continues exactly)."""
        cfg = self.cfg
        rng = rng_state()
        if self.info.distributed:
            gathered = [None] * self.info.world_size
            torch.distributed.all_gather_object(gathered, rng)
            rng = gathered
        return CheckpointContract(
            model=model_state(self.model),   # the plain weights' names, with or without fake int8 (quant.py)
            model_config=cfg.model,
            label_space=LabelSpaceRecord.of_space(self.label_space, Path(self.prompt_path).read_text(encoding="utf-8")),
            bank=self.bank, step=int(self.step), epoch=int(epoch),
            training=TrainingState(self.optimizer.state_dict(), self.scheduler.state_dict(), rng),
            total_steps=int(self.total_steps), world_size=int(self.info.world_size), train_config=plain(cfg.to_dict()),
            rig=self.rig, align_center=self.align_center.cpu() if self.align_center is not None else None,
            calibration=getattr(self, "calibration", None))

    def snapshot_path(self, step: int) -> Path:
        return self.out / "snapshots" / f"step_{step:06d}.pt"

    def save_snapshot(self, epoch: int) -> None:
        """A model-only checkpoint of this step (no optimiser, scheduler or RNG): evaluable and exportable."""
        contract = self.checkpoint_contract(epoch)
        if self.info.is_main:
            contract.model_only().save(self.snapshot_path(self.step))
        D.barrier(self.info)

    def save(self, epoch: int) -> Path | None:
        contract = self.checkpoint_contract(epoch)  # collective in DDP: every rank takes part
        path = None
        if self.info.is_main:
            path = contract.save(self.out / "last.pt")
        D.barrier(self.info)
        return path

    def noise_for_step(self, step: int) -> torch.Tensor | None:
        n = self.cfg.noise_words
        if n <= 0 or not getattr(self.cfg.loss, "use_noise", True):
            return None
        rng = np.random.default_rng([self.cfg.seed, step])
        return torch.as_tensor(np.asarray(self.noise_bank.sample(n, rng), dtype=np.float32), device=self.info.device)

    def voxels_for_step(self, batch: dict, step: int) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """(B, M) voxel sample for the heads and losses and its (B, M) importance weights (None = whole grid,
        or no weights for the "priority" rule); seeded by (seed, step, rank)."""
        if self.cfg.train_voxels <= 0:
            return None, None
        from .losses.sampling import select_stratified, select_training_voxels

        gen = torch.Generator().manual_seed(int(np.random.SeedSequence([self.cfg.seed, step, self.info.rank])
                                                .generate_state(1)[0]))
        if self.cfg.voxel_sampling == "priority":
            return select_training_voxels(batch["semantics"], self.cfg.train_voxels, batch.get("align_index"),
                                          generator=gen), None
        return select_stratified(batch["semantics"], self.cfg.train_voxels, self.cfg.occupied_share, generator=gen)

    def train_step(self, batch: dict) -> dict:
        """One optimiser step on `batch` (the DataLoader's collated dict); returns the loss parts."""
        cfg = self.cfg
        batch = _to_device(batch, self.info.device)
        if self.align_center is not None:
            batch["align_center"] = self.align_center
        noise = self.noise_for_step(self.step)
        index, weight = self.voxels_for_step(batch, self.step)
        diagnose = (self.step + 1) % cfg.log_every == 0   # the step whose loss parts are logged
        out = self.ddp(batch, self.text, self.phrase_class, noise, index, weight, self.class_weight, diagnose)
        loss = out["total"]
        if not torch.isfinite(loss):
            raise FloatingPointError(f"loss is {loss.item()} at step {self.step}")
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), cfg.grad_clip)
        self.optimizer.step()
        self.scheduler.step()
        self.step += 1
        return out

    # -------------------------------------------------------------------------------------------
    def run(self, until: int | None = None) -> dict:
        """Train to `total_steps` (or stop early at step `until`, schedule unchanged, as if interrupted
        right after a checkpoint); returns {"step", "losses": [per-step total], "last": path, ...}."""
        if not hasattr(self, "model"):
            self.setup()
        stop = self.total_steps if until is None else min(int(until), self.total_steps)
        cfg, info = self.cfg, self.info
        if info.is_main:
            self.out.mkdir(parents=True, exist_ok=True)
            cfg.save(self.out / "config.json")
        log_path = self.out / "log.jsonl"
        log_lines = log_path.read_text().splitlines() if (self.resume and info.is_main and log_path.exists()) else []
        log_lines = [ln for ln in log_lines if json.loads(ln).get("step", 0) <= self.step]
        losses: list[float] = []
        self.ddp.train()
        progress = _Progress(self.total_steps, self.step, enabled=info.is_main and not self.quiet)
        epoch = self.step // self.steps_per_epoch
        t_last, cpu_last, last_logged = time.perf_counter(), time.process_time(), self.step
        try:
            while self.step < stop:
                epoch = self.step // self.steps_per_epoch
                skip = self.step - epoch * self.steps_per_epoch
                self.sampler.set_epoch(epoch)
                self.dataset.set_epoch(epoch)
                order = list(self.sampler)[skip * cfg.batch_size:]
                loader = DataLoader(self.dataset, batch_size=cfg.batch_size, sampler=_Resumable(order),
                                    collate_fn=collate, num_workers=loader_workers(cfg.num_workers),
                                    pin_memory=info.device.type == "cuda",
                                    # own generator: creating a loader must not draw from the global RNG
                                    generator=torch.Generator().manual_seed(cfg.seed * 1000 + epoch))
                for batch in loader:
                    if self.step >= stop:
                        break
                    lr_now = self.scheduler.get_last_lr()[-1]  # the rate this step uses (the last group: 1x)
                    out = self.train_step(batch)
                    value = float(out["total"].detach())
                    losses.append(value)
                    progress.advance(value, lr_now)
                    if self.step % cfg.log_every == 0 or self.step == stop:
                        # loss parts averaged over the ranks (a collective: every rank takes part)
                        parts = {k: D.mean_over_ranks(float(v.detach()), info) for k, v in out.items()
                                 if isinstance(v, torch.Tensor) and v.numel() == 1}
                        now, cpu_now = time.perf_counter(), time.process_time()
                        if info.is_main:
                            n_steps = max(1, self.step - last_logged)
                            rec = {"step": self.step, "epoch": epoch, "lr": lr_now,
                                   "sec_per_step": (now - t_last) / n_steps,        # wall clock
                                   "cpu_sec_per_step": (cpu_now - cpu_last) / n_steps,  # this process, all threads
                                   **parts}
                            log_lines.append(json.dumps(rec))
                            write_text(log_path, "\n".join(log_lines) + "\n")
                        t_last, cpu_last, last_logged = now, cpu_now, self.step
                    if cfg.snapshot_steps and self.step in cfg.snapshot_steps:
                        self.save_snapshot(epoch)
                    if self.step % cfg.ckpt_every == 0 and self.step < stop:
                        self.save(epoch)
        finally:
            progress.close()
        if self.step >= self.total_steps and self.info.is_main and self.cfg.quant == "none":
            # the identifier's per-branch logit scales, from known-class training voxels (calibrate.py)
            from .calibrate import fit_scales

            self.calibration = CalibrationRecord.from_payload(fit_scales(self), "calibration", self.cfg.model.embed_dim)
        last = self.save(self.step // self.steps_per_epoch if self.steps_per_epoch else 0)
        return {"step": self.step, "losses": losses, "last": str(last) if last else None,
                "total_steps": self.total_steps, "steps_per_epoch": self.steps_per_epoch}


class _Progress:
    """A rich progress bar showing the loss (rank 0); only on a terminal (ago_runtime.progress.progress_enabled)."""

    def __init__(self, total: int, start: int, enabled: bool):
        from ago_runtime.progress import progress_enabled

        self.enabled = enabled and progress_enabled()
        self.bar = None
        if self.enabled:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self.bar = Progress(TextColumn("train"), BarColumn(), MofNCompleteColumn(),
                                TextColumn("loss {task.fields[loss]:.4f} lr {task.fields[lr]:.2e}"),
                                TimeRemainingColumn(), console=Console(stderr=True))
            self.bar.start()
            self.task = self.bar.add_task("train", total=total, completed=start, loss=float("nan"), lr=0.0)

    def advance(self, loss: float, lr: float) -> None:
        if self.bar is not None:
            self.bar.update(self.task, advance=1, loss=loss, lr=lr)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def train(cfg: TrainConfig, resume: bool = False, quiet: bool = False) -> dict:
    """Run one training (joins the torchrun process group when launched under torchrun)."""
    info = D.setup(cfg.device)
    try:
        return Trainer(cfg, resume=resume, dist_info=info, quiet=quiet).run()
    finally:
        D.cleanup(info)


def recalibrate(run_dir) -> CalibrationRecord:
    """Re-fit the calibration of a finished run's `<run>/last.pt` on its training frames and rewrite the
    checkpoint (atomically; the weights, optimiser and step are kept): `ago calibrate RUN`. For runs made
    before a calibration change (e.g. the adapted branch's standardisation statistics)."""
    from pathlib import Path

    from ago_runtime.errors import AgoInputError

    from .calibrate import fit_scales

    run = Path(run_dir)
    if not (run / "config.json").is_file() or not (run / "last.pt").is_file():
        raise AgoInputError(run, "not a finished `ago train` folder (needs config.json and last.pt)")
    trainer = Trainer(TrainConfig.load(run / "config.json"), resume=True, quiet=True)
    trainer.setup()
    if trainer.step < trainer.total_steps:
        raise AgoInputError(run / "last.pt", f"the run stopped at step {trainer.step} of {trainer.total_steps}; "
                            "finish it with `ago train --resume` (which calibrates at the end)")
    trainer.calibration = CalibrationRecord.from_payload(fit_scales(trainer), "calibration", trainer.cfg.model.embed_dim)
    trainer.save(trainer.step // trainer.steps_per_epoch if trainer.steps_per_epoch else 0)
    return trainer.calibration
