"""Text-space scoring of voxel embeddings (torch; training and evaluation, not exported).

Column order of every logits tensor here:
    [ K label classes | free (index K) | Nn noise words (each its own column) ]
A label class scores the MAX of the dot products with its phrases (prompts); the free column is the
dot product with the learnable free embedding; noise words are negatives seen in training only.

- class_logits(feat (B, N, C), text (P, C), phrase_class (P,), K, free_embedding (C,), noise (Nn, C) | None)
    -> (B, N, K + 1 + Nn)
- open_world_identify(logits_main, logits_adapted, mode, num_classes, scale_main, scale_adapted)
    -> (pred, branch, entropy): occupancy from the main branch, class from the trusted branch
"""

from __future__ import annotations

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


def open_world_identify(logits_main: torch.Tensor, logits_adapted: torch.Tensor,
                        mode: Identifier = Identifier.MIN_ENTROPY,
                        num_classes: int | None = None, scale_main: float = 1.0, scale_adapted: float = 1.0
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per voxel: free or occupied from the main branch, and the class from the branch it trusts: the torch
    form of ago_runtime.predict.decision.decide (the specification; tests/test_decision.py compares them).

    logits_*: (..., K + 1 [+ Nn]) in this module's column order (noise columns are dropped).
    1. Occupancy: the main branch's argmax over [K classes + free] (F_3D is the branch trained on free
       space; F~_3D is aligned only on occupied voxels, so its free column means nothing).
    2. Class of an occupied voxel: P = softmax(scale_main * main[:K]), P~ = softmax(scale_adapted *
       adapted[:K]), both over the K classes (the scales come from ago_train/calibrate.py, fitted on
       known-class training voxels); MIN_ENTROPY takes the branch with the lower entropy (the
       paper's c_v = 1[H(P) <= H(P~)]), MAX_CONF the one with the higher max probability, NONE the
       main one, ADAPTED the adapted one.
    Returns pred (...) int64 in 0..K (K = free), branch (...) int64 (1 = adapted; 0 for free voxels) and
    the chosen branch's class entropy (...).
    """
    K = logits_main.shape[-1] - 1 if num_classes is None else num_classes
    occupied = logits_main[..., : K + 1].argmax(-1) != K
    p_main = torch.softmax(scale_main * logits_main[..., :K].float(), -1)
    p_adap = torch.softmax(scale_adapted * logits_adapted[..., :K].float(), -1)
    h_main, h_adap = entropy(p_main), entropy(p_adap)
    try:
        mode = Identifier(mode)
    except ValueError:
        raise ValueError(f"unknown open-world mode {mode!r}; expected one of {', '.join(Identifier.names())}") from None
    if mode == Identifier.MIN_ENTROPY:
        use_adapted = h_adap < h_main
    elif mode == Identifier.MAX_CONF:
        use_adapted = p_adap.amax(-1) > p_main.amax(-1)
    elif mode == Identifier.NONE:
        use_adapted = torch.zeros_like(h_main, dtype=torch.bool)
    else:
        use_adapted = torch.ones_like(h_main, dtype=torch.bool)
    use_adapted = use_adapted & occupied
    cls = torch.where(use_adapted, p_adap.argmax(-1), p_main.argmax(-1))
    pred = torch.where(occupied, cls, torch.full_like(cls, K))
    return pred, use_adapted.long(), torch.where(use_adapted, h_adap, h_main)
