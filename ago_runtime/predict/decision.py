"""The voxel decision: the one specification, in numpy, of how per-voxel features become a label.

Driven in the runtime by one caller, the slab loop (ago_runtime.predict.classifier.VoxelClassifier, float32:
`ago infer`, `ago retrieve`, the export's parity check; tests/test_architecture.py checks that nothing else in
ago_runtime calls it); also by the export parity reference (ago_export/parity.py: the same functions in float64
on the torch model's embeddings) and compared against the torch training path (ago_train.model.text_logits.decide;
tests/test_decision.py). The names of a decision live here too: `Identifier` (how a voxel's branch is chosen)
and `Branch` (main, adapted); the bundle contract and ago_train import them from here.

Inputs: a prompt bank (P phrase embeddings t_p of width C, phrase p belonging to class k(p) of K) and the
bundle's linear heads (heads.npz, `HeadWeights`): per voxel the main embedding F = h W_dec^T + b_dec
(F_3D) and the adapted embedding F~ = g W_ad^T + b_ad (F~_3D).

1. Score rows (`score_rows`): per branch, P + 1 rows R (P+1, C) and offsets o (P+1,) so that the phrase and
   free scores of an embedding F are s = R F + o; the last row is free.
     main:    R = [t_1 .. t_P; free_embedding],  o = [0 .. 0; free_bias]
     adapted: R = [t_p / sd_p ..; free_embedding], o = [-(m . t_p) / sd_p ..; 0], sd_p = sqrt(t_p' S t_p)
   (`phrase_standardisation`: m, S the mean and covariance of F~ over training voxels, heads.npz
   adapted_mean / adapted_cov; without them sd = 1, m = 0.)
2. Fold (`fold`): R and o into the linear head, s = A x + c with A = R W, c = R b + o, x = h or g; so a bank
   costs one (P+1) x D product per voxel.
3. Class scores (`class_scores`): class k scores the max over its phrases' scores (the vocabulary's one rule,
   ago_runtime.vocab.phrase_layout); the free row stays. Layout is class-major, z (K+1, n): phrases sorted by
   class (`PhraseLayout`), the free row last.
4. The decision (`main_free`, `decide`), for the K user classes (the first K rows; rows K..K_all-1 are
   reference classes that only the unexplained-obstacle score reads):
     free     = the main branch's argmax over [K classes + free] is free (class max < free score)
     P, P~    = softmax over the K classes of scale_main * z_main, scale_adapted * z_adapted
                (heads.npz branch_scales)
     entropy  = H(P) or H(P~) in nats, confidence = max probability, of the branch chosen:
                Identifier.NONE: main; ADAPTED: adapted; MIN_ENTROPY: adapted when H(P~) < H(P);
                MAX_CONF: adapted when max P~ > max P.
     label    = K on free voxels (branch 0, main's entropy and confidence), else the chosen branch's argmax.
   The entropy and confidence are those of the identifier's distributions (over the K classes, scaled) for
   every identifier, "none" included; free voxels carry the main branch's.
5. With volumes (`decide(..., volumes=True)`), the unexplained-obstacle parts over all K_all classes:
   occupancy = 1 - softmax(z_main over [K_all + free])[free]; unexplained = 1 - the largest probability a
   user class gets in a branch's scaled softmax over the K_all classes, max over both branches (ADAPTED:
   the adapted branch's alone).

Every function works on float32 (the runtime) or float64 (the parity reference) alike; arrays named `z`
are class-major (rows = classes, columns = voxels).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import cv2
import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.vocab.phrase_layout import PhraseLayout


# ---- names -------------------------------------------------------------------------------------
class _Name(str, Enum):
    """An enum whose members are their names as strings (`str(m)`, f-strings and JSON give the value)."""

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)


class Identifier(_Name):
    """How a voxel's class is chosen between the two branches (`decide`)."""

    MIN_ENTROPY = "min-entropy"   # the branch whose class distribution has the lower entropy
    MAX_CONF = "max-conf"         # the branch with the higher max probability
    NONE = "none"                 # the main branch (F_3D) alone
    ADAPTED = "adapted"           # the adapted branch (F~_3D) on every occupied voxel

    @property
    def reads_adapted(self) -> bool:
        """Whether this identifier's labels read the adapted branch (every identifier but NONE)."""
        return self is not Identifier.NONE

    @classmethod
    def names(cls) -> list[str]:
        return [i.value for i in cls]

    @classmethod
    def parse(cls, value, source=None) -> "Identifier":
        """`value` (an Identifier or its name) -> Identifier; AgoInputError naming `source` otherwise."""
        try:
            return cls(value)
        except ValueError:
            raise AgoInputError(source, f"must be one of {', '.join(cls.names())}, got {value!r}") from None


class Branch(_Name):
    """The two per-voxel embeddings: F_3D (main, from the decoder's h) and F~_3D (adapted, from the adapter's g)."""

    MAIN = "main"
    ADAPTED = "adapted"



# ---- 1-2. score rows and folding --------------------------------------------------------------
def phrase_standardisation(phrases: np.ndarray, mean: np.ndarray | None, cov: np.ndarray | None
                           ) -> tuple[np.ndarray, np.ndarray]:
    """(P, C) phrase embeddings -> (scale (P,), bias (P,)) float64 so that z = scale * (F~ . t) + bias is the
    phrase's standardised adapted score (F~.t - m.t) / sqrt(t' S t); (1, 0) without statistics."""
    t = np.asarray(phrases, dtype=np.float64)
    if mean is None:
        return np.ones(len(t)), np.zeros(len(t))
    var = np.einsum("pc,cd,pd->p", t, np.asarray(cov, np.float64), t)
    scale = 1.0 / np.sqrt(np.maximum(var, 1e-12))
    return scale, -(t @ np.asarray(mean, np.float64)) * scale


def score_rows(heads, phrases: np.ndarray, branch: Branch) -> tuple[np.ndarray, np.ndarray]:
    """-> (R (P+1, C), o (P+1,)) float64: a branch's phrase and free scores of an embedding F are R F + o
    (see the module doc, step 1). `heads`: a HeadWeights."""
    t = np.asarray(phrases, dtype=np.float64)
    free = np.asarray(heads.free_embedding, np.float64)[None]
    if branch == Branch.MAIN:
        return np.concatenate([t, free]), np.append(np.zeros(len(t)), float(heads.free_bias))
    scale, bias = phrase_standardisation(t, heads.adapted_mean, heads.adapted_cov)
    return np.concatenate([t * scale[:, None], free]), np.append(bias, 0.0)


def fold(heads, phrases: np.ndarray, branch: Branch) -> tuple[np.ndarray, np.ndarray]:
    """-> (A (P+1, D), c (P+1,)) float64: a branch's scores of hidden features x (h or g) are A x + c."""
    R, o = score_rows(heads, phrases, branch)
    W, b = (heads.W_dec, heads.b_dec) if branch == Branch.MAIN else (heads.W_ad, heads.b_ad)
    return R @ np.asarray(W, np.float64), R @ np.asarray(b, np.float64) + o


# ---- 3. class scores ----------------------------------------------------------------------------
def class_scores(s: np.ndarray, c: np.ndarray, layout: PhraseLayout) -> np.ndarray:
    """(P+1, n) scores without their offset, phrases in layout order, free last (overwritten) + c (P+1, 1)
    -> (K_all + 1, n) class scores: the max over each class's phrases (`PhraseLayout.class_max`, the one
    max-over-phrases rule); the last row is free."""
    s += c
    if layout.one_phrase_per_class:
        return s
    out = np.empty((layout.num_classes + 1, s.shape[1]), s.dtype)
    layout.class_max(s[:-1], out=out[:-1])
    out[-1] = s[-1]
    return out


# ---- 4. the decision -----------------------------------------------------------------------------
@dataclass
class SoftmaxStats:
    """Per voxel of a class-major score block: argmax, entropy (nats) and max probability of its softmax."""

    label: np.ndarray       # (n,) intp row index
    entropy: np.ndarray     # (n,)
    confidence: np.ndarray  # (n,)


def first_zero_row(z: np.ndarray) -> np.ndarray:
    """(R, n) -> (n,) intp: per column the first row where z == 0 (R - 1 where none is; the argmax of a block whose
    column maxima were subtracted). Up to 256 rows as bytes: each row where it is zero weighs R - 1 - row, and the
    largest weight is the first such row; numpy's argmax over a short leading axis and a loop of masked row
    assignments are both several times slower."""
    R = z.shape[0]
    if R > 256:
        label = np.full(z.shape[1], R - 1, np.intp)
        for k in range(R - 2, -1, -1):
            label[z[k] == 0.0] = k
        return label
    weight = (z == 0.0).view(np.uint8)
    weight *= np.arange(R - 1, -1, -1, dtype=np.uint8)[:, None]
    return (R - 1) - weight.max(axis=0).astype(np.intp)


def softmax_stats(z: np.ndarray) -> SoftmaxStats:
    """(R, n) scores -> argmax, entropy, max probability over the R rows (z is overwritten)."""
    z -= z.max(axis=0)                      # z <= 0, 0 at the argmax
    label = first_zero_row(z)
    e = cv2.exp(np.ascontiguousarray(z))    # OpenCV's vectorised exp
    total = e.sum(axis=0)                   # >= 1
    entropy = np.log(total) - np.einsum("kn,kn->n", e, z, optimize=False) / total   # log Z - sum p z
    np.maximum(entropy, 0.0, out=entropy)
    return SoftmaxStats(label, entropy.astype(z.dtype, copy=False), (1.0 / total).astype(z.dtype, copy=False))


def main_free(z_main: np.ndarray, num_classes: int) -> np.ndarray:
    """(K_all + 1, n) main class scores -> (n,) bool: free, the main argmax over [K user classes + free] is free
    (a tie goes to the class, as an argmax that takes the first maximum)."""
    return z_main[:num_classes].max(axis=0) < z_main[-1]


def adapted_voxels(free: np.ndarray, identifier: Identifier, volumes: bool = False) -> np.ndarray:
    """The voxels (sorted indices) whose adapted scores `decide` reads: the occupied ones, none for NONE; every
    voxel with volumes (the unexplained-obstacle score reads both branches everywhere)."""
    if volumes:
        return np.arange(len(free))
    if not Identifier(identifier).reads_adapted:
        return np.zeros(0, np.intp)
    return np.flatnonzero(~free)


def _scaled(z: np.ndarray, scale: float) -> np.ndarray:
    z = np.array(z, copy=True, order="C")
    if scale != 1.0:
        z *= z.dtype.type(scale)
    return z


def user_confidence(z: np.ndarray, num_classes: int, scale: float) -> np.ndarray:
    """(K_all, n) class scores -> (n,) the largest probability a user class (rows < K) gets in the scaled
    softmax over all K_all classes (z is not modified)."""
    z = _scaled(z, scale)
    z -= z.max(axis=0)
    e = cv2.exp(z)
    return e[:num_classes].max(axis=0) / e.sum(axis=0)


def occupied_probability(z: np.ndarray) -> np.ndarray:
    """(R, n) class scores, the last row free -> (n,) 1 - softmax(z)[free] (z is not modified)."""
    e = cv2.exp(np.ascontiguousarray(z - z.max(axis=0)))
    return 1.0 - e[-1] / e.sum(axis=0)


@dataclass
class Decision:
    """One block of n voxels decided."""

    label: np.ndarray        # (n,) intp: 0..K-1 class, K free
    entropy: np.ndarray      # (n,) of the chosen branch's distribution over the K classes (scaled)
    confidence: np.ndarray   # (n,) its max probability
    branch: np.ndarray       # (n,) uint8: 0 main, 1 adapted
    occupancy: np.ndarray | None = None     # volumes: 1 - p(free) over [K_all classes + free], main branch
    unexplained: np.ndarray | None = None   # volumes: 1 - best user-class probability, max over branches


def decide(z_main: np.ndarray, free: np.ndarray, z_adapted: np.ndarray | None, need: np.ndarray,
           identifier: Identifier, num_classes: int, scales: tuple[float, float] = (1.0, 1.0),
           volumes: bool = False) -> Decision:
    """The decision of n voxels (module doc, steps 4-5).

    z_main (K_all + 1, n): the main branch's class scores (`class_scores`); free (n,) = `main_free(z_main, K)`;
    z_adapted (K_all + 1, m): the adapted branch's class scores of the voxels `need` (= `adapted_voxels(free,
    identifier, volumes)`), or None when m = 0; num_classes: K, the user's classes (the first K rows).
    z_main and z_adapted are not modified."""
    identifier = Identifier(identifier)
    K, n = int(num_classes), z_main.shape[1]
    scale_main, scale_adapted = float(scales[0]), float(scales[1])
    main = softmax_stats(_scaled(z_main[:K], scale_main))
    label, entropy, confidence = main.label, main.entropy, main.confidence
    branch = np.zeros(n, np.uint8)
    out = Decision(label, entropy, confidence, branch)
    if volumes:
        out.occupancy = occupied_probability(z_main)
        best = user_confidence(z_main[:-1], K, scale_main)
    if len(need):
        if z_adapted is None or z_adapted.shape[1] != len(need):
            raise ValueError(f"the adapted class scores must cover the {len(need)} voxels of `need`")
        ad = softmax_stats(_scaled(z_adapted[:K], scale_adapted))
        if identifier == Identifier.MIN_ENTROPY:
            pick = ad.entropy < entropy[need]
        elif identifier == Identifier.MAX_CONF:
            pick = ad.confidence > confidence[need]
        elif identifier == Identifier.ADAPTED:
            pick = np.ones(len(need), bool)
        else:
            pick = np.zeros(len(need), bool)
        pick &= ~free[need]
        chosen = need[pick]
        branch[chosen] = 1
        label[chosen] = ad.label[pick]
        entropy[chosen] = ad.entropy[pick]
        confidence[chosen] = ad.confidence[pick]
        if volumes:
            conf_ad = user_confidence(z_adapted[:-1], K, scale_adapted)
            best[need] = conf_ad if identifier == Identifier.ADAPTED else np.maximum(best[need], conf_ad)
    label[free] = K
    if volumes:
        out.unexplained = 1.0 - best
    return out
