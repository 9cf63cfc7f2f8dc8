"""Grounding loss: voxel class logits vs 3-D pseudo-labels, cross-entropy + Lovász-softmax.

Pseudo-label semantics are uint8 (.., X, Y, Z) or (.., N): 0..K-1 label classes, 17 = free,
255 = unknown. `semantics_to_targets` turns them into int64 targets for logits whose columns are
[K classes | free | noise]: class k -> k, free -> K, unknown (and any id >= K other than free) -> 255.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ago_runtime.classes import FREE, IGNORE

from .lovasz import lovasz_softmax


def semantics_to_targets(semantics: torch.Tensor, num_classes: int) -> torch.Tensor:
    t = semantics.long()
    return torch.where(t == FREE, torch.full_like(t, num_classes),
                       torch.where(t < num_classes, t, torch.full_like(t, IGNORE)))


def weighted_cross_entropy(logits: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None) -> torch.Tensor:
    """Mean CE over the voxels whose target is not IGNORE; with per-voxel `weight`, the weighted mean
    sum(w_i ce_i) / sum(w_i). logits (M, C'), target (M,), weight (M,) or None -> scalar (0 if none)."""
    valid = target != IGNORE
    if weight is not None:
        valid = valid & (weight > 0)
    if not bool(valid.any()):
        return logits.sum() * 0.0
    if weight is None:
        return F.cross_entropy(logits, target, ignore_index=IGNORE)
    ce = F.cross_entropy(logits, torch.where(valid, target, torch.zeros_like(target)), reduction="none")
    w = torch.where(valid, weight.to(ce.dtype), torch.zeros_like(ce))
    return (ce * w).sum() / w.sum()


def grounding_loss(logits: torch.Tensor, target: torch.Tensor, num_classes: int, lovasz_only_present: bool = True,
                   weight: torch.Tensor | None = None,
                   class_weight: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """logits (B, N, K + 1 + Nn), target (B, N) from semantics_to_targets, weight (B, N) optional per-voxel
    importance weights (a stratified sample's), class_weight (K + 1,) optional CE weights of the classes
    and free (losses/class_balance.py; the CE only) -> (ce, lovasz) scalars.

    Lovász is computed over the K classes + free (noise columns still share the softmax)."""
    flat = logits.reshape(-1, logits.shape[-1])
    tgt = target.reshape(-1)
    w = None if weight is None else weight.reshape(-1)
    w_ce = w
    if class_weight is not None:
        cw = class_weight.to(flat.device, flat.dtype)[torch.where(tgt == IGNORE, torch.zeros_like(tgt), tgt)]
        w_ce = cw if w is None else w.to(cw.dtype) * cw
    ce = weighted_cross_entropy(flat, tgt, w_ce)
    lov = lovasz_softmax(torch.softmax(flat, -1), tgt, ignore_index=IGNORE, only_present=lovasz_only_present,
                         classes=num_classes + 1, weight=w)
    return ce, lov
