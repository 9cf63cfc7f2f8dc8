"""Occupancy loss: a 2-way CE per voxel on [max over the K label classes ; free] logits.

Targets come from semantics_to_targets: 0..K-1 -> occupied (0), K -> free (1), 255 -> ignored.
Noise columns take no part.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ago_runtime.classes import IGNORE


def occupancy_logits(logits: torch.Tensor, num_classes: int) -> torch.Tensor:
    """(.., K + 1 + Nn) -> (.., 2): [max over classes 0..K-1, free]."""
    return torch.stack([logits[..., :num_classes].amax(-1), logits[..., num_classes]], -1)


def occupancy_loss(logits: torch.Tensor, target: torch.Tensor, num_classes: int) -> torch.Tensor:
    occ = occupancy_logits(logits, num_classes).reshape(-1, 2)
    t = target.reshape(-1)
    binary = torch.where(t == IGNORE, torch.full_like(t, IGNORE),
                         (t == num_classes).long())           # 0 occupied, 1 free
    if (binary == IGNORE).all():
        return occ.sum() * 0.0
    return F.cross_entropy(occ, binary, ignore_index=IGNORE)
