"""The bundle's linear heads (heads.npz) and a prompt bank folded into them, in numpy.

`HeadWeights`: W_dec (C, Dh), b_dec (C,), W_ad (C, Da), b_ad (C,), free_embedding (C,), the identifier's
branch scales, the adapted branch's standardisation statistics and the free bias.

`FoldedHeads`: a bank folded into both heads (ago_runtime.predict.decision.fold), as data: a branch's phrase
and free scores of hidden features x (n, D) are A x + c, one (P+1) x D product per voxel. Phrases are
sorted by class (PhraseLayout), so class scores, softmax and argmax are element-wise operations over long
rows of n voxels. The decision itself (identifier, entropy, free) is ago_runtime.predict.decision; its one
driver, the slab loop, is ago_runtime.predict.classifier.VoxelClassifier.

Also: the default identifier of a bank, unfolded embeddings and cosine similarities (retrieval).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ago_runtime.predict import decision
from ago_runtime.predict.contract import HEADS_NPZ
from ago_runtime.predict.decision import Branch, Identifier
from ago_runtime.vocab.phrase_layout import PhraseLayout

DEFAULT_CHUNK = 16384           # voxels per chunk for the unfolded helpers below
SCORE_BUDGET_BYTES = 64 << 20   # a slab's or chunk's (P', n) score block of a folded bank stays under this


def default_identifier(class_names, known, trained_classes,
                       open_world: Identifier = Identifier.MIN_ENTROPY) -> Identifier:
    """The identifier a bank gets when none is asked for (`ago infer`, `ago eval`): `open_world` when
    the bank holds a class unknown to the model - one the model was not trained on, or one outside the
    bank's own known list (a prompt file's `@known:`; without one a parsed file calls every class
    known) - and "none" (the grounded branch F_3D alone) for a closed-world bank: there the adapted
    branch has nothing to add and only flips near-tied voxels (docs/results.md, Tab. 1)."""
    seen = set(trained_classes) & set(known) if known else set(trained_classes)
    return Identifier(open_world) if any(c not in seen for c in class_names) else Identifier.NONE


@dataclass
class HeadWeights:
    """The linear heads of one bundle (heads.npz, whose arrays the contract declares: HEADS_NPZ; each field is the
    array of its name)."""

    W_dec: np.ndarray          # (C, Dh)
    b_dec: np.ndarray          # (C,)
    W_ad: np.ndarray           # (C, Da)
    b_ad: np.ndarray           # (C,)
    free_embedding: np.ndarray  # (C,)
    branch_scales: np.ndarray | None = None   # (2,) identifier logit scales (main, adapted); None = (1, 1)
    # mean (C,) and covariance (C, C) of F~_3D over training voxels (ago_train/calibrate.py): when present,
    # every phrase's adapted score is standardised, z = (F~.t - m.t) / sqrt(t' S t) (phrase_standardisation)
    adapted_mean: np.ndarray | None = None
    adapted_cov: np.ndarray | None = None
    # added to the main branch's free score, F_3D . free_embedding + free_bias (ModelConfig.free_bias; 0 = none)
    free_bias: float = 0.0

    @property
    def scales(self) -> tuple[float, float]:
        if self.branch_scales is None:
            return 1.0, 1.0
        return float(self.branch_scales[0]), float(self.branch_scales[1])

    @property
    def embed_dim(self) -> int:
        return int(self.W_dec.shape[0])

    @property
    def hidden_dim(self) -> int:
        return int(self.W_dec.shape[1])

    @property
    def adapted_dim(self) -> int:
        return int(self.W_ad.shape[1])

    def to_arrays(self) -> dict[str, np.ndarray]:
        """heads.npz's arrays: exactly the names the contract declares (HEADS_NPZ), the optional pair when set."""
        values = {"branch_scales": self.scales, "free_bias": [self.free_bias]}
        names = HEADS_NPZ.names if self.adapted_mean is not None else HEADS_NPZ.required
        return {k: np.asarray(values[k] if k in values else getattr(self, k), dtype=np.float32) for k in names}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> "HeadWeights":
        """The inverse of to_arrays (Bundle.load has checked the names and shapes against HEADS_NPZ)."""
        values = {k: arrays[k] for k in HEADS_NPZ.names if k in arrays}   # each array is the field of its name
        values["free_bias"] = float(values["free_bias"].reshape(-1)[0])
        return cls(**values)


@dataclass(eq=False)
class FoldedHeads:
    """A bank folded into both heads, as data (the slab loop that uses it: ago_runtime.predict.classifier).

    Per branch: A (P+1, D) and c (P+1, 1), the phrases in class order (`layout`) and free last, so that the
    branch's class scores of features x (n, D) are decision.class_scores(A x^T, c, layout) (K_all + 1, n).
    `scales`: the identifier's branch scales. `num_all` = K_all classes, the last `reference_classes` of them
    not the user's (Predictor.fold_with_reference): they never appear in the labels; they only let the
    unexplained-obstacle score see what the model takes a voxel to be when no prompt matches it. Labels,
    entropy and confidence come from the first K = `num_classes` classes + free, exactly as without them.

    `FoldedHeads.fold(weights, phrase_embeddings, phrase_class, num_classes, reference_classes)` makes one
    (float32)."""

    A: dict[Branch, np.ndarray]
    c: dict[Branch, np.ndarray]
    layout: PhraseLayout
    scales: tuple[float, float]
    num_all: int
    reference_classes: int = 0

    @classmethod
    def fold(cls, weights: HeadWeights, phrase_embeddings: np.ndarray, phrase_class: np.ndarray,
             num_classes: int, reference_classes: int = 0) -> "FoldedHeads":
        """The bank (P phrase embeddings, `phrase_class` (P,) in 0..num_classes-1) folded into both heads
        (decision.fold), float32."""
        emb = np.asarray(phrase_embeddings, dtype=np.float32)
        if emb.ndim != 2 or emb.shape[1] != weights.embed_dim:
            raise ValueError(f"bank embeddings {emb.shape} do not match the head width {weights.embed_dim}")
        if np.shape(phrase_class) != (emb.shape[0],):
            raise ValueError("phrase_class must give one class in 0..K-1 per phrase")
        layout = PhraseLayout(phrase_class, num_classes)
        if not 0 <= int(reference_classes) < int(num_classes):
            raise ValueError("reference_classes must leave at least one user class")
        phrases = emb[layout.order]
        A, c = {}, {}
        for branch in Branch:
            A_b, c_b = decision.fold(weights, phrases, branch)
            A[branch] = np.ascontiguousarray(A_b, dtype=np.float32)       # (P+1, D)
            c[branch] = c_b.astype(np.float32)[:, None]                   # (P+1, 1)
        return cls(A, c, layout, weights.scales, int(num_classes), int(reference_classes))

    @property
    def num_classes(self) -> int:
        """K: the user's classes."""
        return self.num_all - self.reference_classes

    @property
    def num_rows(self) -> int:
        return self.layout.num_rows

    def width(self, branch: Branch) -> int:
        """D of a branch: the width of the hidden features its A takes."""
        return int(self.A[Branch(branch)].shape[1])


def embeddings(x: np.ndarray, W: np.ndarray, b: np.ndarray, chunk: int = DEFAULT_CHUNK) -> np.ndarray:
    """Unfolded per-voxel embeddings F = x W^T + b, (N, C) float32 (for retrieval and parity checks)."""
    out = np.empty((x.shape[0], W.shape[0]), np.float32)
    Wt = np.ascontiguousarray(W.T, dtype=np.float32)
    for start in range(0, x.shape[0], chunk):
        sl = slice(start, start + chunk)
        np.matmul(x[sl], Wt, out=out[sl])
        out[sl] += b
    return out


def cosine_to(x: np.ndarray, W: np.ndarray, b: np.ndarray, directions: np.ndarray,
              chunk: int = DEFAULT_CHUNK) -> np.ndarray:
    """Max cosine similarity between each voxel's embedding x W^T + b and the directions (C,) or (P, C)
    -> (N,) float32 (each chunk's embeddings are computed once for all directions)."""
    d = np.asarray(directions, dtype=np.float32).reshape(-1, W.shape[0])
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    Wt = np.ascontiguousarray(W.T, dtype=np.float32)
    dt = np.ascontiguousarray(d.T)
    out = np.empty(x.shape[0], np.float32)
    for start in range(0, x.shape[0], chunk):
        sl = slice(start, start + chunk)
        f = x[sl] @ Wt
        f += b
        norm = np.sqrt(np.einsum("nc,nc->n", f, f))
        out[sl] = (f @ dt).max(axis=1) / np.maximum(norm, 1e-12)
    return out


def phrase_similarity(heads: HeadWeights, h: np.ndarray, g: np.ndarray, branch: np.ndarray,
                      directions: np.ndarray) -> np.ndarray:
    """Per-voxel cosine similarity to a phrase, on each voxel's branch (`ago retrieve`: the adapted one).

    h (N, Dh), g (N, Da): hidden features; branch (N,) 0 = main, 1 = adapted; directions (C,) one phrase
    embedding or (P, C) several (the max over them, as a class's score is the max over its phrases).
    Each voxel is projected on its own branch only. -> (N,) float32."""
    adapted = np.asarray(branch).reshape(-1) == 1
    if adapted.all():
        return cosine_to(g, heads.W_ad, heads.b_ad, directions)
    if not adapted.any():
        return cosine_to(h, heads.W_dec, heads.b_dec, directions)
    out = np.empty(h.shape[0], np.float32)
    out[adapted] = cosine_to(g[adapted], heads.W_ad, heads.b_ad, directions)
    out[~adapted] = cosine_to(h[~adapted], heads.W_dec, heads.b_dec, directions)
    return out
