"""Class-balanced cross-entropy weights from the training pseudo-labels' class counts.

A departure from the paper (which weights its CE uniformly; docs/training.md, "Class balance"): the
synthetic pseudo-labels hold ~700 driveable-surface voxels for each traffic-cone voxel, and the small
object classes (barrier, pedestrian, traffic cone) stay near 0 IoU under a uniform CE. With
`LossConfig.class_balance = a > 0`, an occupied class c with n_c labelled voxels in the TRAINING
pseudo-labels weighs

    w_c = min(cap, s * n_c ** -a),   s chosen so that  sum_c n_c w_c = sum_c n_c

i.e. the weights have a count-weighted mean of 1 over the occupied voxels, so the occupied classes
together keep the mass they had against free space (the stratified sample's occupied : free balance is
unchanged) and only the split among the classes moves. Free space weighs 1. A class absent from the
training labels gets the cap (no voxel of it is ever weighted, so the value only matters for the
record). The counts come from the training split's pseudo-labels only, never from GT or val data.
"""

from __future__ import annotations

import numpy as np

from ago_runtime.classes import FREE

CAP = 10.0


def count_classes(label_arrays, num_classes: int) -> np.ndarray:
    """(K + 1,) int64 voxel counts of the classes 0..K-1 and free (last) over an iterable of uint8
    pseudo-semantics arrays (0..K-1, 17 free, anything else unlabelled and not counted)."""
    counts = np.zeros(num_classes + 1, np.int64)
    for sem in label_arrays:
        b = np.bincount(np.asarray(sem, np.uint8).reshape(-1), minlength=256)
        counts[:num_classes] += b[:num_classes]
        counts[num_classes] += b[FREE]
    return counts


def class_balance_weights(counts, alpha: float, cap: float = CAP) -> np.ndarray:
    """(K + 1,) float32 CE weights (classes, then free = 1) from `count_classes` counts; see the module
    docstring. alpha = 0 gives all ones."""
    counts = np.asarray(counts, np.float64)
    if counts.ndim != 1 or counts.size < 2:
        raise ValueError(f"counts must be (K + 1,), got shape {counts.shape}")
    if alpha < 0:
        raise ValueError(f"class_balance must be >= 0, got {alpha}")
    n = counts[:-1]
    w = np.ones(counts.size, np.float64)
    present = n > 0
    if alpha == 0 or not present.any():
        return w.astype(np.float32)
    raw = np.zeros_like(n)
    raw[present] = n[present] ** -alpha
    # the scale s with sum n_c min(cap, s raw_c) = sum n_c: the left side grows with s; bisect
    total = n.sum()
    lo, hi = 0.0, cap / raw[present].min() * 2 + total
    for _ in range(200):
        s = 0.5 * (lo + hi)
        if (n * np.minimum(cap, s * raw)).sum() < total:
            lo = s
        else:
            hi = s
    cls = np.where(present, np.minimum(cap, hi * raw), cap)
    w[:-1] = cls
    return w.astype(np.float32)
