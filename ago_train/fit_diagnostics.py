"""Two numbers that tell a collapsing model from a learning one, logged by the trainer every `log_every` steps.

- `feature_spread(feat)`: how different the voxel embeddings F_3D are from each other, relative to their
  size: sqrt(mean_v ||f_v - mean f||^2) / mean_v ||f_v|| over the voxels of the batch (or its voxel
  sample). A model whose voxels all map to one vector has spread ~0 and can only predict one class
  everywhere, whatever the loss says.
- `free_share(logits, K)`: the share of those voxels whose argmax over [K classes | free] is free.
  1.0 means "all free".

Both are read without gradients; `benchmarks/fit_check.py` reports them beside the loss and the scores.
"""

from __future__ import annotations

import torch


@torch.no_grad()
def feature_spread(feat: torch.Tensor) -> float:
    """feat (..., N, C) -> the relative spread of the N embeddings (batch dims pooled)."""
    f = feat.detach().reshape(-1, feat.shape[-1]).float()
    centred = f - f.mean(0, keepdim=True)
    return float(centred.pow(2).sum(-1).mean().sqrt() / f.norm(dim=-1).mean().clamp_min(1e-12))


@torch.no_grad()
def free_share(logits: torch.Tensor, num_classes: int) -> float:
    """logits (..., K + 1 [+ noise]) in ago_train.model.text_logits's column order -> share argmax == free."""
    cols = logits.detach()[..., : num_classes + 1]
    return float((cols.argmax(-1) == num_classes).float().mean())
