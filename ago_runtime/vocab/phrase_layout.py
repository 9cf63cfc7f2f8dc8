"""The rule of a bank's class scores: a class scores the max over its phrases' scores (`PhraseLayout.class_max`).

Written once, here, for every user: the runtime's voxel decision (ago_runtime.predict.decision.class_scores,
class-major score blocks of many voxels) and the bank's own class scores (PromptBank.class_scores, phrase
axis last). The torch twin used in training is ago_train.model.text_logits.class_logits (tests/test_decision.py
compares them).
"""

from __future__ import annotations

import numpy as np


class PhraseLayout:
    """Phrases grouped by class: `order` sorts a bank's phrases by class (stable); `row_starts` (K + 1,) are
    the first row of each class in that order and, last, the number of phrases P."""

    def __init__(self, phrase_class: np.ndarray, num_classes: int):
        pc = np.asarray(phrase_class, dtype=np.int64)
        if pc.ndim != 1 or pc.min(initial=0) < 0 or pc.max(initial=0) >= num_classes:
            raise ValueError("phrase_class must give one class in 0..K-1 per phrase")
        counts = np.bincount(pc, minlength=num_classes)
        missing = np.flatnonzero(counts == 0).tolist()
        if missing:
            raise ValueError(f"classes {missing} have no phrase")
        self.order = np.argsort(pc, kind="stable")
        self.row_starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.intp)
        self.one_phrase_per_class = bool(np.all(counts == 1))
        self.in_order = bool(np.array_equal(self.order, np.arange(len(pc))))

    @property
    def num_classes(self) -> int:
        return len(self.row_starts) - 1

    @property
    def num_phrases(self) -> int:
        return int(self.row_starts[-1])

    @property
    def num_rows(self) -> int:
        """Rows of a branch's score block: the P phrases and free."""
        return self.num_phrases + 1

    def class_max(self, s: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """(P, ...) scores, phrases in layout order (rows) -> (K, ...) class scores: the max over each class's
        rows (a loop over classes of row-wise maxima, vectorised over the other axes); into `out` when given."""
        if s.shape[0] != self.num_phrases:
            raise ValueError(f"{s.shape[0]} score rows, the bank has {self.num_phrases} phrases")
        if out is None:
            out = np.empty((self.num_classes,) + s.shape[1:], s.dtype)
        for k, (a, b) in enumerate(zip(self.row_starts[:-1], self.row_starts[1:])):
            if b - a == 1:
                out[k] = s[a]
            else:
                np.max(s[a:b], axis=0, out=out[k])
        return out
