"""Occupancy loss: a 2-way CE per voxel on [max over the K label classes ; free] logits.

Targets come from semantics_to_targets: 0..K-1 -> occupied (0), K -> free (1), 255 -> ignored; or, from
the pseudo semantics directly (`occupancy_binary`), where OCCUPIED_UNLABELLED (254: the LiDAR hit the
voxel, no mask labelled it) is occupied too: the paper's O_binary = 0 if free, 1 otherwise. Those voxels
matter most in the open world, where every class outside the pretraining label space is unlabelled.
Noise columns take no part.
"""

from __future__ import annotations

import torch

from ago_runtime.classes import FREE, IGNORE, OCCUPIED_UNLABELLED

from .grounding import weighted_cross_entropy


def occupancy_logits(logits: torch.Tensor, num_classes: int) -> torch.Tensor:
    """(.., K + 1 + Nn) -> (.., 2): [max over classes 0..K-1, free]."""
    return torch.stack([logits[..., :num_classes].amax(-1), logits[..., num_classes]], -1)


def occupancy_binary(semantics: torch.Tensor, num_classes: int) -> torch.Tensor:
    """Pseudo semantics (0..K-1, 17 free, 254 hit-unlabelled, 255 unknown) -> 0 occupied, 1 free, IGNORE."""
    t = semantics.long()
    occupied = (t < num_classes) | (t == OCCUPIED_UNLABELLED)
    return torch.where(t == FREE, torch.ones_like(t), torch.where(occupied, torch.zeros_like(t),
                                                                  torch.full_like(t, IGNORE)))


def occupancy_loss(logits: torch.Tensor, target: torch.Tensor, num_classes: int,
                   weight: torch.Tensor | None = None, binary: torch.Tensor | None = None) -> torch.Tensor:
    """(.., K + 1 + Nn) logits, (..) grounding targets (or `binary` = occupancy_binary(...) instead),
    optional (..) per-voxel weights -> scalar weighted 2-way CE."""
    occ = occupancy_logits(logits, num_classes).reshape(-1, 2)
    if binary is None:
        t = target.reshape(-1)
        binary = torch.where(t == IGNORE, torch.full_like(t, IGNORE),
                             (t == num_classes).long())           # 0 occupied, 1 free
    return weighted_cross_entropy(occ, binary.reshape(-1), None if weight is None else weight.reshape(-1))
