"""The voxel classification heads in numpy, folded with a prompt bank.

Takes the encoder's hidden features for N voxels, h (N, Dh) and g (N, Da), the bundle's linear
heads (heads.npz: W_dec (C, Dh), b_dec (C,), W_ad (C, Da), b_ad (C,), free_embedding (C,)) and a
prompt bank (P phrase embeddings of width C, each phrase belonging to one of K classes).

The model's per-voxel embeddings are F = h W_dec^T + b_dec (main branch) and
F~ = g W_ad^T + b_ad (adapted branch); a phrase's score is the dot product with its embedding and
the free score the dot product with the learnt free embedding. Both are linear, so when a bank is
loaded we fold them once: with T = [phrase embeddings; free embedding] (P' = P + 1 rows),

    S = F T^T = h (W_dec^T T^T) + b_dec T^T = h A + c,      A: (Dh, P'), c: (P',)

and per voxel only one (Dh x P') product is needed instead of (Dh x C) + (C x P').
Then: class score = max over the class's phrases, softmax over [K classes + free], entropy,
confidence (max probability), argmax. The open-world identifier (ago_train.model.scoring.
open_world_identify, the same rule): a voxel is free when the main branch's argmax over [K + free] is
free; an occupied voxel takes its class from the branch whose class distribution (softmax over the K
classes of `scale * scores`, the per-branch logit scales fitted on known-class training voxels,
heads.npz `branch_scales`) has the lower entropy ("min-entropy"), the higher confidence ("max-conf"),
the main one ("none", which keeps the plain argmax over [K + free]) or the adapted one ("adapted").

Speed: everything works "class-major": scores are computed as S^T (P', n) = A^T h^T, with the
phrases sorted by class, so the max over a class's phrases, the softmax and the argmax are
element-wise operations over long rows of n voxels (numpy is slow at reducing a short last
axis). Voxels are processed in chunks (default: a 64 MiB score block), so memory stays bounded whatever
the grid size.
All float32.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

IDENTIFIERS = ("min-entropy", "max-conf", "none", "adapted")

DEFAULT_CHUNK = 16384           # voxels per chunk for the unfolded helpers below
SCORE_BUDGET_BYTES = 64 << 20   # FoldedHeads: a chunk's (P', n) score block stays under this


def default_identifier(class_names, known, trained_classes, open_world: str = "min-entropy") -> str:
    """The identifier a bank gets when none is asked for (`ago infer`, `ago eval`): `open_world` when
    the bank holds a class unknown to the model - one the model was not trained on, or one outside the
    bank's own known list (a prompt file's `@known:`; without one a parsed file calls every class
    known) - and "none" (the grounded branch F_3D alone) for a closed-world bank: there the adapted
    branch has nothing to add and only flips near-tied voxels (docs/results.md, Tab. 1)."""
    seen = set(trained_classes) & set(known) if known else set(trained_classes)
    return open_world if any(c not in seen for c in class_names) else "none"


@dataclass
class HeadWeights:
    """The linear heads of one bundle (heads.npz)."""

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

    KEYS = ("W_dec", "b_dec", "W_ad", "b_ad", "free_embedding")   # required; the fields above after it optional

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
    def adapter_dim(self) -> int:
        return int(self.W_ad.shape[1])

    def to_arrays(self) -> dict[str, np.ndarray]:
        out = {k: np.asarray(getattr(self, k), dtype=np.float32) for k in self.KEYS}
        out["branch_scales"] = np.asarray(self.scales, dtype=np.float32)
        out["free_bias"] = np.asarray([self.free_bias], dtype=np.float32)
        if self.adapted_mean is not None:
            out["adapted_mean"] = np.asarray(self.adapted_mean, dtype=np.float32)
            out["adapted_cov"] = np.asarray(self.adapted_cov, dtype=np.float32)
        return out

    def adapted_phrase_map(self, phrases: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P, C) phrase embeddings -> (scale (P,), bias (P,)) of the adapted branch's standardisation
        z = scale * (F~.t) + bias with scale = 1/sqrt(t' S t), bias = -(m.t) * scale; (1, 0) without statistics.
        The same map as ago_train.model.scoring.phrase_standardisation, in float64."""
        t = np.asarray(phrases, dtype=np.float64)
        if self.adapted_mean is None:
            return np.ones(len(t)), np.zeros(len(t))
        var = np.einsum("pc,cd,pd->p", t, self.adapted_cov.astype(np.float64), t)
        scale = 1.0 / np.sqrt(np.maximum(var, 1e-12))
        return scale, -(t @ self.adapted_mean.astype(np.float64)) * scale


@dataclass
class BranchResult:
    """Per-voxel outputs of one branch for a chunk of n voxels."""

    label: np.ndarray       # (n,) int64 index into [classes..., free]
    entropy: np.ndarray     # (n,) float32, nats
    confidence: np.ndarray  # (n,) float32, max softmax probability


@dataclass
class MainPart:
    """The main branch's part of a chunk of n voxels (FoldedHeads.main_part), before the adapted branch."""

    identifier: str
    main: BranchResult              # "none": softmax over [K + free]; else the scaled softmax over the K classes
    free: np.ndarray | None         # (n,) bool: the main argmax over [K + free] is free (None for "none")
    need: np.ndarray | None         # (m,) intp: the voxels that need the adapted branch: the occupied ones,
                                    # or all with volumes ("none": None, or all with volumes)
    p_occ: np.ndarray | None = None       # (n,) float32 with volumes: 1 - p(free) over [all classes + free]
    conf_main: np.ndarray | None = None   # (n,) float32 with volumes: the main branch's best user-class probability


class FoldedHeads:
    """A bank folded into both heads; call `classify(h, g)` per chunk or `run(h, g)` on all voxels.

    `phrase_class` (P,) maps each phrase to its class in 0..K-1; the result's class index K is free.
    """

    def __init__(self, weights: HeadWeights, phrase_embeddings: np.ndarray, phrase_class: np.ndarray,
                 num_classes: int, reference_classes: int = 0):
        """`reference_classes` R: the last R of the `num_classes` classes are not the user's but the
        bundle's own training classes that no user class covers (Predictor.fold_with_reference). They
        never appear in the labels; they only let the unexplained-obstacle score see what the model
        takes a voxel to be when no prompt matches it. Labels, entropy and confidence come from the
        first K = num_classes - R classes + free, exactly as without them."""
        emb = np.asarray(phrase_embeddings, dtype=np.float32)
        pc = np.asarray(phrase_class, dtype=np.int64)
        if emb.ndim != 2 or emb.shape[1] != weights.embed_dim:
            raise ValueError(f"bank embeddings {emb.shape} do not match the head width {weights.embed_dim}")
        if pc.shape != (emb.shape[0],) or pc.min(initial=0) < 0 or pc.max(initial=0) >= num_classes:
            raise ValueError("phrase_class must give one class in 0..K-1 per phrase")
        missing = sorted(set(range(num_classes)) - set(pc.tolist()))
        if missing:
            raise ValueError(f"classes {missing} have no phrase")
        order = np.argsort(pc, kind="stable")            # phrases grouped by class
        T = np.concatenate([emb[order], weights.free_embedding[None].astype(np.float32)])  # (P', C)
        if not 0 <= int(reference_classes) < int(num_classes):
            raise ValueError("reference_classes must leave at least one user class")
        self.num_all = int(num_classes)                       # user + reference classes
        self.reference_classes = int(reference_classes)
        self.num_classes = self.num_all - self.reference_classes   # K: the user's classes
        # Row starts of each class (and free, the last row) in the sorted layout, for np.maximum.reduceat.
        counts = np.bincount(pc, minlength=num_classes)
        self.row_starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.intp)  # K_all+1 starts; last = free
        self.one_phrase_per_class = bool(np.all(counts == 1))
        T64 = T.astype(np.float64)
        self.A_main_T = np.ascontiguousarray(T64 @ weights.W_dec.astype(np.float64), dtype=np.float32)  # (P', Dh)
        c_main = T64 @ weights.b_dec.astype(np.float64)
        c_main[-1] += float(weights.free_bias)                      # the free row (last)
        self.c_main = c_main.astype(np.float32)[:, None]                                                  # (P', 1)
        # adapted branch: each phrase row standardised (HeadWeights.adapted_phrase_map); the free row as is
        scale, bias = weights.adapted_phrase_map(T64[:-1])
        scale, bias = np.append(scale, 1.0), np.append(bias, 0.0)
        T_ad = T64 * scale[:, None]
        self.A_ad_T = np.ascontiguousarray(T_ad @ weights.W_ad.astype(np.float64), dtype=np.float32)     # (P', Da)
        self.c_ad = (T_ad @ weights.b_ad.astype(np.float64) + bias).astype(np.float32)[:, None]
        self.scale_main, self.scale_adapted = weights.scales

    @property
    def num_rows(self) -> int:
        return int(self.A_main_T.shape[0])

    # --- one branch ------------------------------------------------------------------------
    def phrase_scores(self, x: np.ndarray, branch: str) -> np.ndarray:
        """(n, D) features -> (P', n) phrase-and-free scores WITHOUT the folded bias c, class-major."""
        A = self.A_main_T if branch == "main" else self.A_ad_T
        return A @ x.T               # BLAS handles the transposed view without a copy

    def class_scores(self, s: np.ndarray, branch: str = "main") -> np.ndarray:
        """(P', n) bias-free scores -> (K+1, n) class scores: bias added, max over each class's phrases;
        the last row is free.

        A loop over classes of row-wise maxima over contiguous rows (vectorised over n): measured
        25x faster than np.maximum.reduceat(s, starts, axis=0) here. The bias is added in the same
        pass (one fewer sweep over the scores).
        """
        c = self.c_main if branch == "main" else self.c_ad
        if self.one_phrase_per_class:
            s += c
            return s
        ends = np.append(self.row_starts[1:], s.shape[0])
        out = np.empty((len(self.row_starts), s.shape[1]), np.float32)
        for k, (a, b) in enumerate(zip(self.row_starts, ends)):
            if b - a == 1:
                np.add(s[a], c[a], out=out[k])
            else:
                rows = s[a:b]
                rows += c[a:b]
                np.max(rows, axis=0, out=out[k])
        return out

    @staticmethod
    def softmax_stats(z: np.ndarray) -> BranchResult:
        """(K+1, n) class scores -> argmax, entropy and max probability per voxel (z is overwritten)."""
        m = z.max(axis=0)
        z -= m                                  # z <= 0, 0 at the argmax
        # argmax = first row where z == 0; a backwards loop of row compares is ~4x faster
        # than np.argmax(z, axis=0) over the short first axis.
        label = np.full(z.shape[1], z.shape[0] - 1, np.intp)
        for k in range(z.shape[0] - 2, -1, -1):
            label[z[k] == 0.0] = k
        e = cv2.exp(np.ascontiguousarray(z))   # OpenCV's vectorised exp: ~5x faster than np.exp here
        total = e.sum(axis=0)                   # >= 1
        # entropy = log Z - sum(p * (z - m)) with p = e / Z
        ez = np.einsum("kn,kn->n", e, z, optimize=False)
        log_total = np.log(total)
        entropy = log_total - ez / total
        np.maximum(entropy, 0.0, out=entropy)
        return BranchResult(label, entropy.astype(np.float32, copy=False),
                            (1.0 / total).astype(np.float32, copy=False))

    # --- both branches + identifier --------------------------------------------------------
    def classify(self, h: np.ndarray, g: np.ndarray, identifier: str = "min-entropy"):
        """One chunk: (n, Dh), (n, Da) -> (label (n,), entropy, confidence, branch (n,) uint8 0=main 1=adapted)."""
        if identifier not in IDENTIFIERS:
            raise ValueError(f"identifier must be one of {IDENTIFIERS}, got {identifier!r}")
        s_ad = None if identifier == "none" else self.phrase_scores(g, "adapted")
        return self.classify_scores(self.phrase_scores(h, "main"), s_ad, identifier)

    def classify_scores(self, s_main: np.ndarray, s_ad: np.ndarray | None, identifier: str = "min-entropy",
                        extras: dict | None = None):
        """Like `classify`, from bias-free class-major phrase scores (P', n) of each branch (overwritten);
        s_ad may be None for "none". The same result as `main_part` + `finish` with s_ad's columns of the
        voxels `main_part` says need the adapted branch (the rest of s_ad is not used)."""
        part = self.main_part(s_main, identifier, volumes=extras is not None)
        sub = None
        if part.need is not None:
            if s_ad is None:
                raise ValueError(f"identifier {identifier!r} needs the adapted branch's scores")
            sub = s_ad if len(part.need) == s_ad.shape[1] else s_ad[:, part.need]
        return self.finish(part, sub, extras)

    def main_part(self, s_main: np.ndarray, identifier: str = "min-entropy", volumes: bool = False) -> "MainPart":
        """The main branch of a chunk, from its bias-free class-major scores (P', n) (overwritten): what the
        identifier takes from it, and which voxels need the adapted branch at all (`MainPart.need`).

        The identifier takes occupancy from the main branch: a voxel whose main argmax over [K classes +
        free] is free is labelled free with the main branch's entropy and confidence (branch 0), whatever
        the adapted branch says. So labels, entropy, confidence and branch need the adapted branch only on
        the voxels the main branch calls occupied. With `volumes` every voxel needs it: the
        unexplained-obstacle score is the max over both branches on every voxel, also on voxels the main
        branch calls free (scored over GT-occupied voxels, the score with the main branch alone there had a
        lower ROC AUC: 0.874 vs 0.907 on 16 synthetic val frames, docs/runtime.md). `finish` takes the
        adapted scores of exactly the voxels in `need`.

        With `volumes`, "occupancy" p_occ = 1 - p(free) of the main branch's softmax over [all classes +
        free] and the main branch's best user-class probability are computed here (see `finish`)."""
        if identifier not in IDENTIFIERS:
            raise ValueError(f"identifier must be one of {IDENTIFIERS}, got {identifier!r}")
        z_all = self.class_scores(s_main, "main")          # (K_all + 1, n), free last
        K, K_all = self.num_classes, self.num_all
        p_occ = conf_main = None
        if volumes:
            # occupancy and "explained" judged with every class the folded bank holds (user + reference)
            p_occ = self._occupied_probability(z_all, K_all)
            conf_main = self._user_confidence(z_all[:K_all], K, self.scale_main)
        z_main = z_all if K == K_all else np.concatenate([z_all[:K], z_all[K_all:]])   # user classes + free
        if identifier == "none":
            # labels from the main branch alone; with volumes the adapted branch still runs on every voxel
            # for the unexplained-obstacle score, which is the max over both branches whatever the identifier
            need = np.arange(z_main.shape[1]) if volumes else None
            return MainPart(identifier, self.softmax_stats(z_main), None, need, p_occ, conf_main)
        free = z_main[:K].max(axis=0) < z_main[K]
        main = self.softmax_stats(self._scaled(z_main[:K], self.scale_main))   # overwrites z_main[:K]
        need = np.arange(len(free)) if volumes else np.flatnonzero(~free)
        return MainPart(identifier, main, free, need, p_occ, conf_main)

    def finish(self, part: "MainPart", s_ad: np.ndarray | None, extras: dict | None = None):
        """-> (label (n,), entropy, confidence, branch (n,) uint8 0=main 1=adapted) of a chunk, from its
        `main_part` and the adapted branch's bias-free scores (P', m) of the voxels `part.need` (in that
        order; overwritten; None or m = 0 when no voxel needs it).

        On an occupied voxel the identifier picks the branch ("min-entropy": the lower entropy of the
        scaled class distributions, "max-conf": the higher confidence, "adapted": always the adapted one);
        free voxels take the main branch's values. With `extras` (a dict), also puts there, per voxel (n,)
        float32, the UNEXPLAINED-OBSTACLE parts: "occupancy" p_occ (see `main_part`), and "unexplained" =
        1 - the largest probability a user class gets in a branch's calibrated softmax over all classes, the
        max over both branches ("adapted": the adapted branch's), also with "none", whose labels come from
        the main branch alone; `main_part` with volumes puts every voxel in `need`, a voxel outside it
        would get the main branch's. "All
        classes" = the user's K plus the reference classes (see __init__)."""
        main = part.main
        n = len(main.label)
        K, K_all = self.num_classes, self.num_all
        if part.identifier == "none":
            if extras is not None:
                best = part.conf_main
                if part.need is not None and len(part.need):      # volumes: need = every voxel
                    if s_ad is None or s_ad.shape[1] != len(part.need) or len(part.need) != n:
                        raise ValueError("with volumes the adapted scores must cover every voxel")
                    z_ad = self.class_scores(s_ad, "adapted")
                    best = np.maximum(best, self._user_confidence(z_ad[:K_all], K, self.scale_adapted))
                extras["occupancy"], extras["unexplained"] = part.p_occ, (1.0 - best).astype(np.float32)
            return main.label, main.entropy, main.confidence, np.zeros(n, np.uint8)
        label, entropy, confidence = main.label, main.entropy, main.confidence   # owned by `part`: updated in place
        use_ad = np.zeros(n, bool)
        best = part.conf_main.copy() if extras is not None else None
        need = part.need
        if len(need):
            if s_ad is None or s_ad.shape[1] != len(need):
                raise ValueError(f"the adapted scores must cover the {len(need)} voxels of part.need")
            z_ad = self.class_scores(s_ad, "adapted")
            conf_ad = self._user_confidence(z_ad[:K_all], K, self.scale_adapted) if extras is not None else None
            ad = self.softmax_stats(self._scaled(z_ad[:K], self.scale_adapted))
            if part.identifier == "min-entropy":
                pick = ad.entropy < entropy[need]
            elif part.identifier == "max-conf":
                pick = ad.confidence > confidence[need]
            else:
                pick = np.ones(len(need), bool)
            pick &= ~part.free[need]
            chosen = need[pick]
            use_ad[chosen] = True
            label[chosen] = ad.label[pick]
            entropy[chosen] = ad.entropy[pick]
            confidence[chosen] = ad.confidence[pick]
            if extras is not None:
                best[need] = conf_ad if part.identifier == "adapted" else np.maximum(best[need], conf_ad)
        label[part.free] = K
        if extras is not None:
            extras["occupancy"], extras["unexplained"] = part.p_occ, (1.0 - best).astype(np.float32)
        return label, entropy, confidence, use_ad.astype(np.uint8)

    @staticmethod
    def _user_confidence(z: np.ndarray, K: int, scale: float) -> np.ndarray:
        """(K_all, n) class scores -> (n,) the largest probability a user class (rows < K) gets in the
        calibrated softmax over all K_all classes (z is not modified)."""
        z = z * np.float32(scale)
        z -= z.max(axis=0)
        e = cv2.exp(np.ascontiguousarray(z))
        return (e[:K].max(axis=0) / e.sum(axis=0)).astype(np.float32)

    @staticmethod
    def _occupied_probability(z: np.ndarray, K: int) -> np.ndarray:
        """(K+1, n) class scores (last row free) -> (n,) 1 - softmax(z)[free]."""
        m = z.max(axis=0)
        e = cv2.exp(np.ascontiguousarray(z - m))
        return (1.0 - e[K] / e.sum(axis=0)).astype(np.float32)

    @staticmethod
    def _scaled(z: np.ndarray, scale: float) -> np.ndarray:
        z = np.ascontiguousarray(z)
        if scale != 1.0:
            z *= np.float32(scale)
        return z

    @property
    def default_chunk(self) -> int:
        """Voxels per chunk: the (P', n) score block within SCORE_BUDGET_BYTES, 8192..131072 voxels.

        Large chunks mean few BLAS calls; measured on this 2-core machine under load, 131072-voxel
        chunks were 1.4x faster than 16384 (each multi-threaded BLAS call has a fixed cost).
        """
        return int(np.clip(SCORE_BUDGET_BYTES // (4 * self.num_rows), 8192, 131072))

    def run(self, h: np.ndarray, g: np.ndarray, identifier: str = "min-entropy",
            chunk: int | None = None) -> dict[str, np.ndarray]:
        """All N voxels, in chunks -> dict of (N,) arrays: label (uint8/uint16), entropy, confidence, branch."""
        chunk = int(chunk or self.default_chunk)
        n = h.shape[0]
        if g.shape[0] != n:
            raise ValueError(f"h has {n} voxels but g has {g.shape[0]}")
        label_dtype = np.uint8 if self.num_classes + 1 <= 255 else np.uint16
        out = {"label": np.empty(n, label_dtype), "entropy": np.empty(n, np.float32),
               "confidence": np.empty(n, np.float32), "branch": np.empty(n, np.uint8)}
        for start in range(0, n, chunk):
            sl = slice(start, min(n, start + chunk))
            label, ent, conf, br = self.classify(h[sl], g[sl], identifier)
            out["label"][sl] = label
            out["entropy"][sl] = ent
            out["confidence"][sl] = conf
            out["branch"][sl] = br
        return out

    def flops_per_voxel(self, identifier: str = "min-entropy") -> int:
        """Multiply-adds x 2 of the folded matmuls per voxel (the dominant cost)."""
        f = 2 * self.A_main_T.shape[0] * self.A_main_T.shape[1]
        if identifier != "none":
            f += 2 * self.A_ad_T.shape[0] * self.A_ad_T.shape[1]
        return f


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
