"""Lovász-softmax loss (Berman, Rannen Triki, Blaschko, CVPR 2018), written from the paper.

For a class c, with per-voxel foreground indicator y_i in {0, 1} and error m_i = |y_i - p_i(c)|, the
loss is the Lovász extension of the Jaccard loss at m: sort m descending (permutation pi), and take
sum_i m_pi(i) * g_i where g_i = J(pi(1..i)) - J(pi(1..i-1)) and J(A) = 1 - |gt minus A| / |gt union A|
(the Jaccard loss when the voxels A are the mispredicted ones). At one-hot probabilities it equals
1 - IoU of that class exactly. The result is the mean over classes (only the classes present in the
labels by default).

With per-voxel `weight` w_i > 0 (the importance weights of a stratified voxel sample,
ago_train/losses/sampling.py) every count in J becomes a sum of weights (|A| -> sum_{i in A} w_i), the
weighted Jaccard loss, whose extension equals 1 - weighted IoU at one-hot probabilities; a positive
modular measure keeps the set function submodular, so the extension stays its convex closure.
"""

from __future__ import annotations

import torch


def lovasz_grad(gt_sorted: torch.Tensor, weight_sorted: torch.Tensor | None = None) -> torch.Tensor:
    """gt_sorted (n,) float 0/1 in the order of decreasing error (and the voxels' weights in that order)
    -> (n,) gradient of the (weighted) Jaccard extension."""
    w = torch.ones_like(gt_sorted) if weight_sorted is None else weight_sorted
    fg = gt_sorted * w
    gts = fg.sum()
    intersection = gts - fg.cumsum(0)
    union = gts + (w - fg).cumsum(0)
    jaccard = 1.0 - intersection / union
    if gt_sorted.numel() > 1:
        jaccard = torch.cat([jaccard[:1], jaccard[1:] - jaccard[:-1]])
    return jaccard


def lovasz_softmax(prob: torch.Tensor, target: torch.Tensor, ignore_index: int | None = 255,
                   only_present: bool = True, classes: int | None = None,
                   weight: torch.Tensor | None = None) -> torch.Tensor:
    """prob (M, K') class probabilities (rows sum to 1), target (M,) int64 in 0..K'-1 or ignore_index,
    weight (M,) optional positive per-voxel weights (see the module docstring).

    `classes`: evaluate only columns 0..classes-1 (e.g. to leave noise columns out); default all.
    Returns a scalar (0 when nothing is labelled)."""
    prob = prob.reshape(-1, prob.shape[-1])
    target = target.reshape(-1)
    if weight is not None:
        weight = weight.reshape(-1).to(prob.dtype)
    if ignore_index is not None:
        keep = target != ignore_index
        if weight is not None:
            keep = keep & (weight > 0)
            weight = weight[keep]
        prob, target = prob[keep], target[keep]
    if target.numel() == 0:
        return prob.sum() * 0.0
    n_cls = prob.shape[1] if classes is None else classes
    losses = []
    for c in range(n_cls):
        fg = (target == c).to(prob.dtype)
        if only_present and fg.sum() == 0:
            continue
        err = (fg - prob[:, c]).abs()
        err_sorted, perm = torch.sort(err, descending=True)
        losses.append(torch.dot(err_sorted, lovasz_grad(fg[perm], None if weight is None else weight[perm])))
    if not losses:
        return prob.sum() * 0.0
    return torch.stack(losses).mean()
