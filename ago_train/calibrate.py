"""Logit scales of the two branches for the open-world identifier, fitted on KNOWN-class TRAINING voxels.

The identifier compares the entropies of two class distributions per voxel: P from F_3D and P~ from
the adapted F~_3D. F_3D is trained by cross-entropy, so the length of its dot products (the sharpness
of P) is learnt; F~_3D is trained by a cosine loss, so the length of its dot products is arbitrary and
P~ can be flat for no reason. A fair comparison needs both calibrated: for each branch one scale s with
P = softmax(s * logits over the K classes), chosen to minimise the negative log-likelihood of the
pseudo-label class over labelled occupied voxels of training frames. Only training frames and only
the classes of the training label space take part (never val data, GT or unknown-class labels); the
result is two numbers the runtime multiplies in (`bundle heads`, docs/runtime.md).

Before the scales, `fit_scales` also takes the mean and covariance of F~_3D over the visible occupied
voxels of the same training frames (the voxels the alignment loss sees; no labels at all). With them
the adapted branch's phrase scores are standardised (model/text_logits.py, `phrase_standardisation`; a
departure from the paper, docs/training.md), and its scale is fitted on the standardised logits.

`fit_scales(trainer, max_frames=16, voxels_per_frame=4000)` -> {"scale_main", "scale_adapted",
"nll_main", "nll_adapted", "voxels", "frames", "adapted_mean" (C,), "adapted_cov" (C, C) (float32
tensors; absent when the run has no aligned voxels), "adapted_voxels"}.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .model.text_logits import adapted_logits, class_logits, class_probabilities, entropy

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


def entropy_matched_scale(logits: torch.Tensor, target_entropy: float) -> float:
    """(M, K) logits -> the scale s with mean entropy of softmax(s * logits) equal to `target_entropy`
    (bisection in log s; the mean entropy falls monotonically as s grows). Clamped to SCALE_GRID's range."""
    logits = logits.double()

    def mean_entropy(s: float) -> float:
        return float(entropy(class_probabilities(logits, s)).mean())

    lo, hi = float(SCALE_GRID[0]), float(SCALE_GRID[-1])
    if mean_entropy(lo) <= target_entropy:
        return lo
    if mean_entropy(hi) >= target_entropy:
        return hi
    for _ in range(60):
        mid = math.sqrt(lo * hi)
        if mean_entropy(mid) > target_entropy:
            lo = mid
        else:
            hi = mid
    return math.sqrt(lo * hi)


@torch.no_grad()
def fit_scales(trainer, max_frames: int = 16, voxels_per_frame: int = 4000, adapted_rule: str = "nll") -> dict:
    """Scales of both branches from the trainer's training frames (see the module docstring).
    `adapted_rule`: "nll" (the adapted scale minimising the NLL, the default) or "entropy" (the scale that
    gives P~ the main branch's mean entropy on the same voxels); both values are recorded either way."""
    if adapted_rule not in ("nll", "entropy"):
        raise ValueError(f"unknown adapted_rule {adapted_rule!r}; expected 'nll' or 'entropy'")
    model, dev = trainer.model, trainer.info.device
    K = trainer.label_space.num_classes
    was = model.training
    model.eval()
    gen = torch.Generator().manual_seed(trainer.cfg.seed)
    n = len(trainer.dataset)
    order = torch.randperm(n, generator=gen)[: min(max_frames, n)].tolist()
    main, feats_adapted, target = [], [], []
    stat_sum, stat_outer, stat_n = None, None, 0
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
            # one forward pass for the labelled voxels (scales) and this frame's visible occupied voxels
            # (those with an E_3D: the statistics of F~_3D, no labels)
            vis = batch.get("align_index")
            vis = vis[torch.randperm(vis.numel(), generator=gen)[:voxels_per_frame]].long() \
                if vis is not None and vis.numel() else torch.zeros(0, dtype=torch.long)
            index = torch.cat([pick, vis])
            out = model(images, batch["ego2img"].to(dev), index[None].to(dev), prefix, adapted=True)
            free = out["free_embedding"]
            n = pick.numel()
            main.append(class_logits(out["feat"][:, :n], trainer.text, trainer.phrase_class, K, free,
                                     None)[0, :, :K].cpu())
            feats_adapted.append(out["feat_adapted"][0, :n].cpu())
            target.append(sem[pick].long())
            if vis.numel():
                fa = out["feat_adapted"][0, n:].double().cpu()
                stat_sum = fa.sum(0) if stat_sum is None else stat_sum + fa.sum(0)
                stat_outer = fa.T @ fa if stat_outer is None else stat_outer + fa.T @ fa
                stat_n += fa.shape[0]
    finally:
        trainer.dataset.augment = saved_aug
        trainer.dataset.epoch = saved_epoch
        model.train(was)
    if not target:
        return {"scale_main": 1.0, "scale_adapted": 1.0, "voxels": 0, "frames": 0}
    t = torch.cat(target)
    stats: dict = {}
    if stat_n > 1:
        mean = stat_sum / stat_n
        cov = (stat_outer - stat_n * torch.outer(mean, mean)) / (stat_n - 1)
        stats = {"adapted_mean": mean.float(), "adapted_cov": cov.float(), "adapted_voxels": stat_n}
    s_main, nll_main = best_scale(torch.cat(main), t)
    ad = adapted_logits(torch.cat(feats_adapted)[None], trainer.text.cpu(), trainer.phrase_class.cpu(), K,
                        model.free_embedding.detach().cpu(), stats)[0, :, :K]
    s_ad, nll_ad = best_scale(ad, t)
    out = {"scale_main": s_main, "scale_adapted": s_ad, "nll_main": nll_main, "nll_adapted": nll_ad,
           "voxels": int(t.numel()), "frames": len(order), **stats}
    # the main branch's mean entropy at its fitted scale on the same voxels, and the adapted scale that
    # gives the adapted branch that mean entropy (adapted_rule "entropy")
    h_main = float(entropy(class_probabilities(torch.cat(main).double(), s_main)).mean())
    out["entropy_main"] = h_main
    out["scale_adapted_nll"] = s_ad
    out["scale_adapted_entropy"] = entropy_matched_scale(ad, h_main)
    if adapted_rule == "entropy":
        out["scale_adapted"] = out["scale_adapted_entropy"]
    out["adapted_rule"] = adapted_rule
    return out

