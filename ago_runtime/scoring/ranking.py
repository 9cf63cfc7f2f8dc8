"""Ranking metrics for per-voxel scores: average precision (retrieval) and ROC AUC (a detector's score).

- `average_precision(scores, positives)`: AP of ranking the items by decreasing score, the area under
  the precision-recall curve as a step function over the distinct score thresholds
  (sum over thresholds of (recall_t - recall_{t-1}) * precision_t); items tied on a score enter together.
  A random ranking scores the positives' prevalence in expectation; a perfect one 1.
- `roc_auc(scores, labels)`: probability that a random positive outscores a random negative (ties
  count one half), i.e. the Mann-Whitney U statistic divided by n_pos * n_neg.
Both take 1-D arrays of any float scores and bool (or 0/1) labels; NaN when a class is empty.
"""

from __future__ import annotations

import numpy as np


def average_precision(scores: np.ndarray, positives: np.ndarray) -> float:
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    y = np.asarray(positives, dtype=bool).reshape(-1)
    if s.shape != y.shape:
        raise ValueError(f"scores {s.shape} and labels {y.shape} differ")
    n_pos = int(y.sum())
    if n_pos == 0:
        return float("nan")
    order = np.argsort(-s, kind="stable")
    s, y = s[order], y[order]
    tp = np.cumsum(y)
    last = np.r_[np.flatnonzero(np.diff(s) != 0), len(s) - 1]     # last item of each run of equal scores
    tp_t = tp[last].astype(np.float64)
    n_t = (last + 1).astype(np.float64)
    recall = tp_t / n_pos
    precision = tp_t / n_t
    return float(np.sum(np.diff(np.r_[0.0, recall]) * precision))


def roc_auc(scores: np.ndarray, labels: np.ndarray) -> float:
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    y = np.asarray(labels, dtype=bool).reshape(-1)
    if s.shape != y.shape:
        raise ValueError(f"scores {s.shape} and labels {y.shape} differ")
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    order = np.argsort(s, kind="stable")
    ranks = np.empty(len(s), np.float64)
    sorted_s = s[order]
    # mid-ranks for ties
    starts = np.r_[0, np.flatnonzero(np.diff(sorted_s) != 0) + 1]
    ends = np.r_[starts[1:], len(s)]
    mid = (starts + ends - 1) / 2.0 + 1.0
    ranks[order] = np.repeat(mid, ends - starts)
    u = ranks[y].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * n_neg))
