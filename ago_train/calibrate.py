"""Logit scales of the two branches for the open-world identifier, fitted on KNOWN-class TRAINING voxels.

The identifier compares the entropies of two class distributions per voxel: P from F_3D and P~ from
the adapted F~_3D. F_3D is trained by cross-entropy, so the length of its dot products (the sharpness
of P) is learnt; F~_3D is trained by a cosine loss, so the length of its dot products is arbitrary and
P~ can be flat for no reason. A fair comparison needs both calibrated: for each branch one scale s with
P = softmax(s * logits over the K classes), chosen to minimise the negative log-likelihood of the
pseudo-label class over labelled occupied voxels of training frames. Only training frames and only
the classes of the training label space take part (never val data, GT or unknown-class labels); the
result is two numbers the runtime multiplies in (`bundle heads`, docs/runtime.md).

`fit_scales(trainer, max_frames=16, voxels_per_frame=4000)` -> {"scale_main", "scale_adapted",
"nll_main", "nll_adapted", "voxels", "frames"}.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .model.scoring import class_logits

SCALE_GRID = np.exp(np.linspace(math.log(1e-2), math.log(1e3), 81))


def best_scale(logits: torch.Tensor, target: torch.Tensor) -> tuple[float, float]:
    """(M, K) logits, (M,) targets in 0..K-1 -> (s, nll) minimising mean NLL of softmax(s * logits)."""
    logits = logits.double()

    def nll(s: float) -> float:
        return float(torch.nn.functional.cross_entropy(s * logits, target))

    values = [nll(s) for s in SCALE_GRID]
    i = int(np.argmin(values))
    lo, hi = SCALE_GRID[max(i - 1, 0)], SCALE_GRID[min(i + 1, len(SCALE_GRID) - 1)]
    for _ in range(30):   # golden-section refinement in log space
        a = math.exp(math.log(lo) + 0.382 * (math.log(hi) - math.log(lo)))
        b = math.exp(math.log(lo) + 0.618 * (math.log(hi) - math.log(lo)))
        if nll(a) < nll(b):
            hi = b
        else:
            lo = a
    s = math.sqrt(lo * hi)
    return s, nll(s)


@torch.no_grad()
def fit_scales(trainer, max_frames: int = 16, voxels_per_frame: int = 4000) -> dict:
    """Scales of both branches from the trainer's training frames (see the module docstring)."""
    model, dev = trainer.model, trainer.info.device
    K = trainer.label_space.num_classes
    was = model.training
    model.eval()
    gen = torch.Generator().manual_seed(trainer.cfg.seed)
    n = len(trainer.dataset)
    order = torch.randperm(n, generator=gen)[: min(max_frames, n)].tolist()
    main, adapted, target = [], [], []
    from .dataset import collate

    saved_epoch, saved_aug = trainer.dataset.epoch, trainer.dataset.augment
    trainer.dataset.augment = "none"
    try:
        for i in order:
            batch = collate([trainer.dataset[i]])
            sem = batch["semantics"][0]
            cand = torch.nonzero(sem < K).reshape(-1)          # labelled voxels of a training class
            if cand.numel() == 0:
                continue
            pick = cand[torch.randperm(cand.numel(), generator=gen)[:voxels_per_frame]]
            prefix = [p.reshape(-1, *p.shape[2:]).float().to(dev) for p in batch["prefix"]] if "prefix" in batch \
                else None
            images = batch["images"].to(dev) if "images" in batch else None
            out = model(images, batch["ego2img"].to(dev), pick[None].to(dev), prefix, adapted=True)
            free = out["free_embedding"]
            main.append(class_logits(out["feat"], trainer.text, trainer.phrase_class, K, free, None)[0, :, :K].cpu())
            adapted.append(class_logits(out["feat_adapted"], trainer.text, trainer.phrase_class, K, free,
                                        None)[0, :, :K].cpu())
            target.append(sem[pick].long())
    finally:
        trainer.dataset.augment = saved_aug
        trainer.dataset.epoch = saved_epoch
        model.train(was)
    if not target:
        return {"scale_main": 1.0, "scale_adapted": 1.0, "voxels": 0, "frames": 0}
    t = torch.cat(target)
    s_main, nll_main = best_scale(torch.cat(main), t)
    s_ad, nll_ad = best_scale(torch.cat(adapted), t)
    return {"scale_main": s_main, "scale_adapted": s_ad, "nll_main": nll_main, "nll_adapted": nll_ad,
            "voxels": int(t.numel()), "frames": len(order)}
