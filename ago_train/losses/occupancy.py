"""Occupancy loss: a 2-way CE per voxel on [max over the K label classes ; free] logits.

Targets come from semantics_to_targets: 0..K-1 -> occupied (0), K -> free (1), 255 -> ignored.
Noise columns take no part.
"""

from __future__ import annotations

import torch

from ago_runtime.classes import IGNORE

from .grounding import weighted_cross_entropy


def occupancy_logits(logits: torch.Tensor, num_classes: int) -> torch.Tensor:
    """(.., K + 1 + Nn) -> (.., 2): [max over classes 0..K-1, free]."""
    return torch.stack([logits[..., :num_classes].amax(-1), logits[..., num_classes]], -1)


def occupancy_loss(logits: torch.Tensor, target: torch.Tensor, num_classes: int,
                   weight: torch.Tensor | None = None) -> torch.Tensor:
    """(.., K + 1 + Nn) logits, (..) targets, optional (..) per-voxel weights -> scalar weighted 2-way CE."""
    occ = occupancy_logits(logits, num_classes).reshape(-1, 2)
    t = target.reshape(-1)
    binary = torch.where(t == IGNORE, torch.full_like(t, IGNORE),
                         (t == num_classes).long())           # 0 occupied, 1 free
    return weighted_cross_entropy(occ, binary, None if weight is None else weight.reshape(-1))
