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


def grounding_loss(logits: torch.Tensor, target: torch.Tensor, num_classes: int, lovasz_only_present: bool = True,
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """logits (B, N, K + 1 + Nn), target (B, N) from semantics_to_targets -> (ce, lovasz) scalars.

    Lovász is computed over the K classes + free (noise columns still share the softmax)."""
    flat = logits.reshape(-1, logits.shape[-1])
    tgt = target.reshape(-1)
    if (tgt != IGNORE).any():
        ce = F.cross_entropy(flat, tgt, ignore_index=IGNORE)
    else:
        ce = flat.sum() * 0.0
    lov = lovasz_softmax(torch.softmax(flat, -1), tgt, ignore_index=IGNORE, only_present=lovasz_only_present,
                         classes=num_classes + 1)
    return ce, lov
