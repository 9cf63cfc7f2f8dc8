"""Choosing a fixed-size voxel sample per frame for training (the heads then run on M, not N, voxels).

select_training_voxels(semantics (B, N) or (B, X, Y, Z), num, align_index=None, generator=None)
  -> (B, M) int64 flat voxel indices, M = min(num, N), no repeats within a frame.
Priority: align voxels (E_3D available) > labelled occupied > labelled free > unknown; random
within a priority level.
"""

from __future__ import annotations

import torch

from ago_runtime.classes import FREE, IGNORE


def select_training_voxels(semantics: torch.Tensor, num: int, align_index: torch.Tensor | None = None,
                           generator: torch.Generator | None = None) -> torch.Tensor:
    B = semantics.shape[0]
    sem = semantics.reshape(B, -1).long().cpu()
    N = sem.shape[1]
    score = torch.rand(B, N, generator=generator)
    score = score + (sem == FREE).float() + 2.0 * ((sem != FREE) & (sem != IGNORE)).float()
    if align_index is not None and align_index.numel():
        bonus = torch.zeros(B * N)
        bonus[align_index.long().cpu()] = 3.0
        score = score + bonus.view(B, N)
    return torch.topk(score, min(num, N), dim=1).indices.to(semantics.device)
