"""Alignment loss between voxel embeddings and dense VLM image embeddings lifted to voxels (E_3D).

feat (M, C) voxel embeddings at the visible occupied voxels, target (M, C) their E_3D.
"cosine": mean(1 - cos), "mse": mean squared error, "l1": mean absolute error (ablation options).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

ALIGN_LOSSES = ("cosine", "mse", "l1")


def align_loss(feat: torch.Tensor, target: torch.Tensor, kind: str = "cosine",
               weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over the M voxels (a weighted mean with per-voxel `weight` (M,), e.g. a stratified sample's)."""
    if kind not in ALIGN_LOSSES:
        raise ValueError(f"unknown align loss {kind!r}; expected one of {ALIGN_LOSSES}")
    if feat.shape[0] == 0:
        return feat.sum() * 0.0
    target = target.to(feat.dtype)
    if kind == "cosine":
        per = 1.0 - F.cosine_similarity(feat, target, dim=-1, eps=1e-6)
    elif kind == "mse":
        per = (feat - target).square().mean(-1)
    else:
        per = (feat - target).abs().mean(-1)
    if weight is None:
        return per.mean()
    w = weight.to(per.dtype)
    return (per * w).sum() / w.sum().clamp_min(1e-12)
