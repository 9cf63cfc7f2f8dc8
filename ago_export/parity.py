"""Parity of an exported encoder (onnxruntime) against the torch model, on one frame.

Takes the torch model, an onnxruntime encoder (ago_runtime.predict.encoder.SplitEncoder), the bundle's heads and a prompt bank, and one
preprocessed frame (images (1, 6, 3, H, W), ego2img (1, 6, 4, 4)). Gives a JSON-able report:

- `rel_err_feat`, `rel_err_feat_adapted`: max |F_ort - F_torch| / max |F_torch| for the per-voxel
  embeddings F_3D = decoder_out(h) and F~_3D = adapter_out(g) (torch: `model.forward`; ORT: the
  encoder's h, g through the heads in numpy);
- `agreement_main`, `agreement_adapted`, `agreement_identifier`: share of voxels whose argmax class
  (K bank classes + free) agrees between the torch reference (`reference_labels`: the voxel decision
  of ago_runtime.predict.decision in float64 on the torch embeddings, unfolded) and the runtime's own
  path (`runtime_labels`: the bank folded into the heads, the encoder slab by slab, VoxelClassifier),
  for the original branch, the adapted branch and the min-entropy identifier;
- `ok` and the tolerances used.

Tolerances (documented in docs/runtime.md): float32 export rel err <= 1e-3 and agreement >= 99.9 %;
int8 (dynamic quantisation) rel err <= 0.25 and agreement >= 85 % (int8 is an opt-in speed trade).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ago_runtime.predict import decision
from ago_runtime.predict.classifier import VoxelClassifier
from ago_runtime.predict.decision import Branch, Identifier
from ago_runtime.predict.heads import FoldedHeads, HeadWeights, embeddings
from ago_runtime.vocab.phrase_layout import PhraseLayout


@dataclass(frozen=True)
class Tolerance:
    max_rel_err: float
    min_agreement: float


FP32_TOLERANCE = Tolerance(1e-3, 0.999)
INT8_TOLERANCE = Tolerance(0.25, 0.85)


def reference_labels(feat: np.ndarray, feat_ad: np.ndarray, bank, heads: HeadWeights,
                     identifier: Identifier = Identifier.MIN_ENTROPY) -> dict[str, np.ndarray]:
    """The float64 reference from the per-voxel embeddings F (N, C), F~ (N, C): each branch's argmax over
    [K classes + free] ("main", "adapted") and the identifier's labels, by the voxel decision
    (ago_runtime.predict.decision) with the bank applied to the embeddings directly (unfolded)."""
    layout = PhraseLayout(bank.phrase_class, bank.num_classes)
    phrases = np.asarray(bank.embeddings)[layout.order]
    out, z = {}, {}
    for branch, f in ((Branch.MAIN, feat), (Branch.ADAPTED, feat_ad)):
        R, o = decision.score_rows(heads, phrases, branch)
        z[branch] = decision.class_scores(R @ f.astype(np.float64).T, o[:, None], layout)   # (K+1, N)
        out[branch.value] = decision.softmax_stats(z[branch].copy()).label
    K = bank.num_classes
    free = decision.main_free(z[Branch.MAIN], K)
    need = decision.adapted_voxels(free, identifier)
    z_ad = z[Branch.ADAPTED][:, need] if len(need) else None
    out["identifier"] = decision.decide(z[Branch.MAIN], free, z_ad, need, identifier, K, heads.scales).label
    return out


def runtime_labels(encoder, folded: FoldedHeads, images: np.ndarray, ego2img: np.ndarray,
                   identifier: Identifier = Identifier.MIN_ENTROPY) -> dict[str, np.ndarray]:
    """Labels the way `ago infer` gets them, all from the runtime's slab loop (VoxelClassifier): "identifier"
    (`classify`: the adapted branch only where the main branch calls a voxel occupied); "main" and "adapted"
    (`branch_labels`: each branch's folded scores on every voxel, through the class max and argmax)."""
    classifier = VoxelClassifier(encoder)
    labels = classifier.branch_labels(images, ego2img, folded)
    labels["identifier"] = classifier.classify(images, ego2img, folded, identifier)[0]["label"]
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
    del ref
    # slab by slab (the runtime's slabs): the ONNX embeddings and the float64 reference of a slab at a time,
    # so the check holds no whole-grid copy beyond torch's two embedding volumes
    err = {"F": 0.0, "F~": 0.0}
    scale = {"F": float(np.abs(feat_t).max()), "F~": float(np.abs(feat_ad_t).max())}
    parts: dict[str, list] = {}
    for start, stop, h, g in encoder.chunks(images, ego2img):
        ft, fat = feat_t[start:stop], feat_ad_t[start:stop]
        err["F"] = max(err["F"], float(np.abs(embeddings(h, heads.W_dec, heads.b_dec) - ft).max()))
        err["F~"] = max(err["F~"], float(np.abs(embeddings(g, heads.W_ad, heads.b_ad) - fat).max()))
        for key, labels in reference_labels(ft, fat, bank, heads).items():
            parts.setdefault(key, []).append(labels)
    want = {key: np.concatenate(v) for key, v in parts.items()}

    def rel(which):
        return err[which] / max(scale[which], 1e-12)

    folded = FoldedHeads.fold(heads, bank.embeddings, bank.phrase_class, bank.num_classes)
    got = runtime_labels(encoder, folded, images, ego2img)
    report = {
        "frame": frame,
        "num_voxels": int(feat_t.shape[0]),
        "rel_err_feat": rel("F"),
        "rel_err_feat_adapted": rel("F~"),
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
