"""Choosing a fixed-size voxel sample per frame for training (the heads then run on M, not N, voxels).

Two rules (`TrainConfig.voxel_sampling`):

- "stratified" (the default): the sample is drawn from the LABELLED voxels only (pseudo-label class,
  OCCUPIED_UNLABELLED = hit by the LiDAR without a class, or free; unknown voxels are ignored by every
  loss, so sampling them is wasted work) in two strata,
  occupied and free. Each stratum gets `occupied_share` resp. 1 - `occupied_share` of the M slots
  (a stratum with too few voxels gives its unused slots to the other), drawn uniformly without
  repeats, and every sampled voxel carries the importance weight

        w = (n_s / n_labelled) / (m_s / M)        (n_s voxels in its stratum, m_s of them sampled)

  so that weighted losses over the sample estimate the losses over the whole labelled grid: the
  weighted occupied : free proportion equals the pseudo-labels' own, whatever `occupied_share` is
  (that only trades variance between the strata). Weights have mean 1 over the sample.
  `select_stratified(semantics, num, occupied_share, generator)` -> (index (B, M), weight (B, M)).
- "priority" (the older rule): align voxels > labelled occupied > labelled free > unknown,
  random within a level, no weights. It fills the sample with occupied voxels first, so a frame
  whose labelled grid is ~20 % occupied is seen ~45 % occupied: the model learns that most space is
  full. Kept for the ablation (benchmarks/results/training_cpu.md).
  `select_training_voxels(semantics, num, align_index=None, generator=None)` -> (B, M) indices.

`M = min(num, N)` for "priority"; for "stratified" M = num exactly (repeats only when a frame has
fewer than `num` labelled voxels, each repeat splitting its weight), so batches keep one shape.
"""

from __future__ import annotations

import torch

from ago_runtime.classes import FREE, IGNORE

SAMPLING_RULES = ("stratified", "priority")


def select_training_voxels(semantics: torch.Tensor, num: int, align_index: torch.Tensor | None = None,
                           generator: torch.Generator | None = None) -> torch.Tensor:
    """The "priority" rule (see the module docstring)."""
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


def _draw(candidates: torch.Tensor, m: int, generator: torch.Generator | None) -> torch.Tensor:
    """m of `candidates` (1-D int64) uniformly without repeats (with repeats only if m > len)."""
    n = candidates.numel()
    if m <= 0 or n == 0:
        return candidates[:0]
    if m <= n:
        return candidates[torch.randperm(n, generator=generator)[:m]]
    reps = torch.randint(n, (m - n,), generator=generator)
    return torch.cat([candidates, candidates[reps]])


def select_stratified(semantics: torch.Tensor, num: int, occupied_share: float = 0.5,
                      generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The "stratified" rule (see the module docstring): -> (index (B, num) int64, weight (B, num) float32)."""
    if not 0.0 < occupied_share < 1.0:
        raise ValueError(f"occupied_share must be in (0, 1), got {occupied_share}")
    B = semantics.shape[0]
    sem = semantics.reshape(B, -1).long().cpu()
    index = torch.empty(B, num, dtype=torch.long)
    weight = torch.empty(B, num, dtype=torch.float32)
    for b in range(B):
        occ = torch.nonzero((sem[b] != FREE) & (sem[b] != IGNORE)).reshape(-1)   # classes + OCCUPIED_UNLABELLED
        free = torch.nonzero(sem[b] == FREE).reshape(-1)
        n_occ, n_free = occ.numel(), free.numel()
        n_lab = n_occ + n_free
        if n_lab == 0:           # nothing labelled: any voxels, weight 0 (every loss ignores them anyway)
            index[b] = torch.randint(sem.shape[1], (num,), generator=generator)
            weight[b] = 0.0
            continue
        m_occ = int(round(num * occupied_share))
        m_occ = min(m_occ, n_occ) if n_free > 0 else num
        m_occ = max(m_occ, num - n_free) if n_occ > 0 else 0
        m_occ = min(m_occ, num)
        m_free = num - m_occ
        picks = [_draw(occ, m_occ, generator), _draw(free, m_free, generator)]
        w = [torch.full((m_occ,), (n_occ / n_lab) * num / max(m_occ, 1)),
             torch.full((m_free,), (n_free / n_lab) * num / max(m_free, 1))]
        index[b] = torch.cat(picks)
        weight[b] = torch.cat(w)
    return index.to(semantics.device), weight.to(semantics.device)
