"""Class logits of voxel embeddings against the text embeddings, and the open-world identifier (torch; training
and evaluation, not exported).

Column order of every logits tensor here:
    [ K label classes | free (index K) | Nn noise words (each its own column) ]
A label class scores the MAX of the dot products with its phrases (prompts); the free column is the
dot product with the learnable free embedding; noise words are negatives seen in training only.

- class_logits(feat (B, N, C), text (P, C), phrase_class (P,), K, free_embedding (C,), noise (Nn, C) | None)
    -> (B, N, K + 1 + Nn)
- decide(logits_main, logits_adapted | None, identifier, num_classes, scales)
    -> Decision (label, branch, entropy, and both branches' entropies): occupancy from the main branch,
    class from the branch the identifier trusts; the one scorer of the torch side
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ago_runtime.predict.decision import Identifier

NO_PHRASE_SCORE = -1e4  # a class without any phrase scores this (finite, so CE/softmax stay defined)


def class_logits(feat: torch.Tensor, text: torch.Tensor, phrase_class: torch.Tensor, num_classes: int,
                 free_embedding: torch.Tensor, noise: torch.Tensor | None = None,
                 phrase_bias: torch.Tensor | None = None, free_bias: torch.Tensor | None = None) -> torch.Tensor:
    """feat (B, N, C) -> logits (B, N, K + 1 + Nn) in the column order of this module.
    `phrase_bias` (P,) is added to each phrase's dot product (the adapted branch's standardisation),
    `free_bias` () to the free column (ModelConfig.free_bias; None = none)."""
    phrase_class = phrase_class.reshape(-1).to(feat.device, torch.long)
    if phrase_class.numel() and (phrase_class.min() < 0 or phrase_class.max() >= num_classes):
        raise ValueError(f"phrase classes must lie in 0..{num_classes - 1}")
    phrase_scores = feat @ text.to(feat.dtype).T                                  # (B, N, P)
    if phrase_bias is not None:
        phrase_scores = phrase_scores + phrase_bias.to(feat.device, feat.dtype)
    B, N, P = phrase_scores.shape
    # each class: the max over its phrases, one scatter over the P columns (no (N, K, Pmax) gather)
    cls = phrase_scores.new_full((B, N, num_classes), float("-inf")).scatter_reduce(
        -1, phrase_class.view(1, 1, P).expand(B, N, P), phrase_scores, reduce="amax", include_self=True)
    has_phrase = torch.zeros(num_classes, dtype=torch.bool, device=feat.device)
    has_phrase[phrase_class] = True
    cls = torch.where(has_phrase, cls, torch.full_like(cls, NO_PHRASE_SCORE))
    free = feat @ free_embedding.to(feat.dtype)
    if free_bias is not None:
        free = free + free_bias.to(feat.dtype)
    cols = [cls, free.unsqueeze(-1)]
    if noise is not None and noise.shape[0] > 0:
        cols.append(feat @ noise.to(feat.dtype).T)
    return torch.cat(cols, -1)


def phrase_standardisation(text: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor
                           ) -> tuple[torch.Tensor, torch.Tensor]:
    """Per phrase t: the affine map that standardises its dot products with the adapted embedding,
    z = (x.t - m.t) / sqrt(t' S t), where m (C,) and S (C, C) are the mean and covariance of F~_3D over
    training voxels (ago_train/calibrate.py; no labels). -> (text scaled by 1/sd (P, C), bias -m.t/sd (P,)).

    Why: the adapted branch is aligned with image embeddings, not trained to rank classes against each
    other, so some phrases score high on every voxel (their dot product with the mean embedding); a
    class's voxels rank high for its phrase (retrieval works) while the argmax across phrases is taken
    by those generic phrases. Standardising each phrase's score over the training distribution makes the
    phrases comparable, for any bank, with no retraining (the runtime folds the same map into the bank)."""
    t = text.double()
    sd = torch.einsum("pc,cd,pd->p", t, cov.double(), t).clamp_min(1e-12).sqrt()
    return (t / sd[:, None]).to(text.dtype), (-(t @ mean.double()) / sd).to(text.dtype)


def adapted_logits(feat_adapted: torch.Tensor, text: torch.Tensor, phrase_class: torch.Tensor, num_classes: int,
                   free_embedding: torch.Tensor, stats: dict | None = None) -> torch.Tensor:
    """Class logits of the adapted branch (B, N, K + 1): phrase-standardised when `stats` holds the
    training statistics {"adapted_mean" (C,), "adapted_cov" (C, C)} of F~_3D, plain dot products otherwise.
    The free column stays the plain dot product with the free embedding (the identifier never reads it)."""
    if not stats or "adapted_mean" not in stats:
        return class_logits(feat_adapted, text, phrase_class, num_classes, free_embedding, None)
    mean = torch.as_tensor(stats["adapted_mean"], dtype=torch.float32, device=feat_adapted.device)
    cov = torch.as_tensor(stats["adapted_cov"], dtype=torch.float32, device=feat_adapted.device)
    scaled, bias = phrase_standardisation(text.to(feat_adapted.device), mean, cov)
    return class_logits(feat_adapted, scaled, phrase_class, num_classes, free_embedding, None, phrase_bias=bias)


def entropy(prob: torch.Tensor, dim: int = -1) -> torch.Tensor:
    return -(prob * torch.log(prob.clamp_min(1e-12))).sum(dim)


def class_probabilities(logits: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """(..., K) class logits -> the identifier's class distribution softmax(scale * logits) (..., K), in the
    logits' dtype."""
    return torch.softmax(scale * logits, -1)


@dataclass
class Decision:
    """`decide`'s result, per voxel (...): the torch twin of ago_runtime.predict.decision.Decision."""

    label: torch.Tensor                     # int64 in 0..K (K = free)
    branch: torch.Tensor                    # int64: 1 = adapted (0 for free voxels)
    entropy: torch.Tensor                   # of the chosen branch's class distribution
    entropy_main: torch.Tensor              # H(P), every voxel
    entropy_adapted: torch.Tensor | None    # H(P~), every voxel; None without adapted logits


def decide(logits_main: torch.Tensor, logits_adapted: torch.Tensor | None,
           identifier: Identifier = Identifier.MIN_ENTROPY, num_classes: int | None = None,
           scales: tuple[float, float] = (1.0, 1.0)) -> Decision:
    """Per voxel: free or occupied from the main branch, and the class from the branch the identifier
    trusts: the torch form of ago_runtime.predict.decision.decide (the specification; tests/test_decision.py
    compares them), and the one scorer of the torch side (`ago eval`, the experiments).

    logits_*: (..., K + 1 [+ Nn]) in this module's column order (noise columns are dropped); logits_adapted
    may be None for an identifier that does not read it (`Identifier.reads_adapted`: NONE).
    1. Occupancy: the main branch's argmax over [K classes + free] (F_3D is the branch trained on free
       space; F~_3D is aligned only on occupied voxels, so its free column means nothing).
    2. Class of an occupied voxel: P = softmax(scale_main * main[:K]), P~ = softmax(scale_adapted *
       adapted[:K]), both over the K classes (the scales come from ago_train/calibrate.py, fitted on
       known-class training voxels); MIN_ENTROPY takes the branch with the lower entropy (the
       paper's c_v = 1[H(P) <= H(P~)]), MAX_CONF the one with the higher max probability, NONE the
       main one, ADAPTED the adapted one. A branch's class is its argmax over the K class logits.
    Returns both branches' entropies beside the chosen one's (the experiments' statistics read them).
    """
    try:
        identifier = Identifier(identifier)
    except ValueError:
        raise ValueError(f"unknown open-world mode {identifier!r}; expected one of {', '.join(Identifier.names())}") \
            from None
    if logits_adapted is None and identifier.reads_adapted:
        raise ValueError(f"identifier {identifier} reads the adapted branch: give its logits")
    K = logits_main.shape[-1] - 1 if num_classes is None else num_classes
    occupied = logits_main[..., : K + 1].argmax(-1) != K
    p_main = class_probabilities(logits_main[..., :K].float(), scales[0])
    h_main = entropy(p_main)
    cls = logits_main[..., :K].argmax(-1)
    use_adapted = torch.zeros_like(occupied)
    h_adap = None
    if logits_adapted is not None:
        p_adap = class_probabilities(logits_adapted[..., :K].float(), scales[1])
        h_adap = entropy(p_adap)
        if identifier == Identifier.MIN_ENTROPY:
            use_adapted = h_adap < h_main
        elif identifier == Identifier.MAX_CONF:
            use_adapted = p_adap.amax(-1) > p_main.amax(-1)
        elif identifier == Identifier.ADAPTED:
            use_adapted = torch.ones_like(occupied)
        use_adapted = use_adapted & occupied
        cls = torch.where(use_adapted, logits_adapted[..., :K].argmax(-1), cls)
    label = torch.where(occupied, cls, torch.full_like(cls, K))
    chosen = h_main if h_adap is None else torch.where(use_adapted, h_adap, h_main)
    return Decision(label, use_adapted.long(), chosen, h_main, h_adap)
