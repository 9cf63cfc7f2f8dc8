"""Parity of an exported encoder (onnxruntime) against the torch model, on one frame.

Takes the torch model, an onnxruntime encoder (ago_runtime.predict.encoder.SplitEncoder), the bundle's heads and a prompt bank, and one
preprocessed frame (images (1, 6, 3, H, W), ego2img (1, 6, 4, 4)). Gives a JSON-able report:

- `rel_err_feat`, `rel_err_feat_adapted`: max |F_ort - F_torch| / max |F_torch| for the per-voxel
  embeddings F_3D = decoder_out(h) and F~_3D = adapter_out(g) (torch: `model.forward`; ORT: the
  encoder's h, g through the heads in numpy);
- `agreement_main`, `agreement_adapted`, `agreement_identifier`: share of voxels whose argmax class
  (K bank classes + free) agrees between the torch reference (float64 scores from the torch
  embeddings, computed directly, unfolded) and the runtime's own path (`runtime_labels`: the bank
  folded into the heads, scores from the encoder slab by slab, numpy class max and softmax),
  for the original branch, the adapted branch and the min-entropy identifier;
- `ok` and the tolerances used.

Tolerances (documented in docs/runtime.md): float32 export rel err <= 1e-3 and agreement >= 99.9 %;
int8 (dynamic quantisation) rel err <= 0.25 and agreement >= 85 % (int8 is an opt-in speed trade).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ago_runtime.predict.heads import FoldedHeads, HeadWeights, embeddings


@dataclass(frozen=True)
class Tolerance:
    max_rel_err: float
    min_agreement: float


FP32_TOLERANCE = Tolerance(1e-3, 0.999)
INT8_TOLERANCE = Tolerance(0.25, 0.85)


def reference_labels(feat: np.ndarray, feat_ad: np.ndarray, bank, free: np.ndarray,
                     scales: tuple[float, float] = (1.0, 1.0), adapted_stats: tuple | None = None,
                     free_bias: float = 0.0) -> dict[str, np.ndarray]:
    """Unfolded float64 reference: per-voxel argmax (K classes + free) per branch, and the min-entropy
    identifier's labels by the rule of ago_train.model.scoring.open_world_identify (occupancy from the
    main branch, class from the branch whose scaled class distribution has the lower entropy).
    `adapted_stats` (mean (C,), cov (C, C)): the adapted phrase scores are standardised, (s - m.t) / sqrt(t'St)."""
    T = np.concatenate([bank.embeddings, free[None]]).astype(np.float64)       # (P+1, C)
    out, zs = {}, {}
    for name, f in (("main", feat), ("adapted", feat_ad)):
        s = f.astype(np.float64) @ T.T                                          # (N, P+1)
        if name == "adapted" and adapted_stats is not None:
            m, S = (np.asarray(a, dtype=np.float64) for a in adapted_stats)
            P = T.shape[0] - 1
            sd = np.sqrt(np.einsum("pc,cd,pd->p", T[:P], S, T[:P]))
            s[:, :P] = (s[:, :P] - T[:P] @ m) / sd
        if name == "main":
            s[:, -1] += free_bias
        z = np.concatenate([bank.class_scores(s[:, :-1]), s[:, -1:]], axis=1)   # (N, K+1)
        out[name] = z.argmax(axis=1)
        zs[name] = z
    K = zs["main"].shape[1] - 1
    ent, cls = {}, {}
    for (name, z), scale in zip(zs.items(), scales):
        c = scale * z[:, :K]
        c = c - c.max(axis=1, keepdims=True)
        p = np.exp(c)
        p /= p.sum(axis=1, keepdims=True)
        ent[name] = -(p * np.log(np.maximum(p, 1e-300))).sum(axis=1)
        cls[name] = c.argmax(axis=1)
    occupied = out["main"] != K
    pick = np.where(ent["adapted"] < ent["main"], cls["adapted"], cls["main"])
    out["identifier"] = np.where(occupied, pick, K)
    return out


def runtime_labels(encoder, folded: FoldedHeads, images: np.ndarray, ego2img: np.ndarray) -> dict[str, np.ndarray]:
    """Labels the way `ago infer` gets them: "identifier" from the runtime's own slab loop (the adapted
    branch only where the main branch calls a voxel occupied: ago_runtime.predict.predictor.classify_slabs);
    "main" and "adapted" from both branches' scores on every voxel (the encoder's score_chunks), each through
    the numpy class max / softmax."""
    from ago_runtime.predict.predictor import classify_slabs

    out: dict[str, list] = {"main": [], "adapted": []}
    for _start, _stop, s_main, s_ad in encoder.score_chunks(images, ego2img, folded):
        out["main"].append(folded.softmax_stats(folded.class_scores(s_main, "main")).label)
        out["adapted"].append(folded.softmax_stats(folded.class_scores(s_ad, "adapted")).label)
    labels = {k: np.concatenate(v) for k, v in out.items()}
    labels["identifier"] = classify_slabs(encoder, folded, images, ego2img, "min-entropy", label_dtype=np.int64)[0]["label"]
    return labels


def check_parity(model, encoder, heads: HeadWeights, bank, images: np.ndarray, ego2img: np.ndarray,
                 tolerance: Tolerance = FP32_TOLERANCE, frame: str = "") -> dict:
    """The torch model read out on the encoder's grid (encoder.grid: the model's own or a finer read-out grid)
    against the runtime's slab loop on the same frame."""
    import torch

    with torch.no_grad():
        ref = model(torch.from_numpy(images), torch.from_numpy(ego2img), grid_shape=tuple(encoder.grid.shape))
    feat_t = ref["feat"][0].numpy()
    feat_ad_t = ref["feat_adapted"][0].numpy()
    h, g = encoder.hidden(images, ego2img)
    feat_o = embeddings(h, heads.W_dec, heads.b_dec)
    feat_ad_o = embeddings(g, heads.W_ad, heads.b_ad)

    def rel(a, b):
        return float(np.abs(a - b).max() / max(float(np.abs(b).max()), 1e-12))

    stats = None if heads.adapted_mean is None else (heads.adapted_mean, heads.adapted_cov)
    want = reference_labels(feat_t, feat_ad_t, bank, heads.free_embedding, heads.scales, stats, heads.free_bias)
    folded = FoldedHeads(heads, bank.embeddings, bank.phrase_class, bank.num_classes)
    got = runtime_labels(encoder, folded, images, ego2img)
    report = {
        "frame": frame,
        "num_voxels": int(h.shape[0]),
        "rel_err_feat": rel(feat_o, feat_t),
        "rel_err_feat_adapted": rel(feat_ad_o, feat_ad_t),
        "agreement_main": float(np.mean(got["main"] == want["main"])),
        "agreement_adapted": float(np.mean(got["adapted"] == want["adapted"])),
        "agreement_identifier": float(np.mean(got["identifier"] == want["identifier"])),
        "tolerance": {"max_rel_err": tolerance.max_rel_err, "min_agreement": tolerance.min_agreement},
    }
    worst_err = max(report["rel_err_feat"], report["rel_err_feat_adapted"])
    worst_agree = min(report["agreement_main"], report["agreement_adapted"], report["agreement_identifier"])
    report["ok"] = bool(worst_err <= tolerance.max_rel_err and worst_agree >= tolerance.min_agreement)
    return report


def describe(report: dict) -> str:
    return (f"rel err F {report['rel_err_feat']:.2e}, F~ {report['rel_err_feat_adapted']:.2e}; argmax agreement "
            f"main {report['agreement_main']:.4%}, adapted {report['agreement_adapted']:.4%}, "
            f"identifier {report['agreement_identifier']:.4%} (tolerance: rel err <= "
            f"{report['tolerance']['max_rel_err']:g}, agreement >= {report['tolerance']['min_agreement']:.1%})")
