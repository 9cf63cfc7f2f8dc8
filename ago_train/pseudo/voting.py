"""Semantic voting and per-voxel feature means.

Takes points already turned into flat voxel indices (C order over Grid.shape) with a label or
a feature each; gives one label / one mean feature per voxel. Everything is done over the
distinct occupied voxels only (np.unique + np.bincount / np.add.reduceat), never over the whole grid.
"""

from __future__ import annotations

import numpy as np


def vote(flat_index: np.ndarray, labels: np.ndarray, num_labels: int) -> tuple[np.ndarray, np.ndarray]:
    """Majority label per voxel.

    flat_index (N,) int, labels (N,) ints in 0..num_labels-1 -> (voxels (U,) int64 sorted, label (U,) int64).
    Ties go to the smaller label index (np.argmax takes the first maximum).
    """
    flat_index = np.asarray(flat_index, dtype=np.int64)
    labels = np.asarray(labels, dtype=np.int64)
    if flat_index.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    voxels, inverse = np.unique(flat_index, return_inverse=True)
    counts = np.bincount(inverse * num_labels + labels, minlength=len(voxels) * num_labels)
    return voxels, counts.reshape(len(voxels), num_labels).argmax(axis=1)


class FeatureMean:
    """Running per-voxel sum and count of point features, merged frame by frame.

    add(flat_index (N,), feats (N, C)); result() -> (index (M,) int64 sorted, mean (M, C) float32).
    Memory stays at (distinct voxels so far) x C.
    """

    def __init__(self):
        self.index = np.zeros(0, dtype=np.int64)
        self.sums: np.ndarray | None = None
        self.counts = np.zeros(0, dtype=np.int64)

    @staticmethod
    def _reduce(index: np.ndarray, feats: np.ndarray, counts: np.ndarray):
        order = np.argsort(index, kind="stable")
        index, feats, counts = index[order], feats[order], counts[order]
        starts = np.flatnonzero(np.r_[True, index[1:] != index[:-1]])
        return index[starts], np.add.reduceat(feats, starts, axis=0), np.add.reduceat(counts, starts)

    def add(self, flat_index: np.ndarray, feats: np.ndarray) -> None:
        """Add per-point features (N, C) of points in voxels flat_index (N,)."""
        flat_index = np.asarray(flat_index, dtype=np.int64)
        if flat_index.size == 0:
            return
        self.add_sums(*self._reduce(flat_index, np.asarray(feats, dtype=np.float32),
                                    np.ones(len(flat_index), dtype=np.int64)))

    def add_sums(self, index: np.ndarray, sums: np.ndarray, counts: np.ndarray) -> None:
        """Add per-voxel feature sums (U, C) over counts (U,) points, voxels index (U,) (distinct)."""
        if len(index) == 0:
            return
        if self.sums is None:
            self.index, self.sums, self.counts = (np.asarray(index, np.int64), np.asarray(sums, np.float32),
                                                  np.asarray(counts, np.int64))
            return
        self.index, self.sums, self.counts = self._reduce(
            np.concatenate([self.index, index]), np.concatenate([self.sums, np.asarray(sums, np.float32)]),
            np.concatenate([self.counts, counts]))

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        if self.sums is None:
            return np.zeros(0, np.int64), np.zeros((0, 0), np.float32)
        return self.index, self.sums / self.counts[:, None].astype(np.float32)
