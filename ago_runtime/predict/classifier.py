"""`VoxelClassifier`: the slab loop, the one place where the encoder's features meet the voxel decision.

Data flows one way, slab by slab (n voxels of whole x-rows):

    planes (once a frame) -> h = the decoder's stages (every voxel) -> z_main = the main branch's class scores
    -> free = decision.main_free -> need = decision.adapted_voxels -> g = the adapter's stages on those voxels
    -> z_adapted -> decision.decide -> label, entropy, confidence, branch (+ occupancy, unexplained)

The encoder (ago_runtime.predict.encoder) only runs graphs, the folded heads (ago_runtime.predict.heads)
only hold the folded bank, and the rule is ago_runtime.predict.decision. The whole grid's features never
exist at once: memory follows the slab.
"""

from __future__ import annotations

import time

import numpy as np

from ago_runtime.predict import decision
from ago_runtime.predict.contract import Branch, Identifier
from ago_runtime.predict.heads import FoldedHeads


class FrameFeatures:
    """What a frame's prediction computes that no bank changes, kept to re-query that frame with other banks
    (`Predictor.predict_arrays(..., features=...)`): the TPV planes (planes.onnx) and the decoder's h of every
    voxel, slab by slab (the bank enters only after h: its products with h and g, the heads). A re-query then
    runs only the bank products, the adapter's stages on the voxels that need them, and the heads.

    Memory: h costs 4 * Dh bytes a voxel (100x100x8, Dh 128: 41 MB; 200x200x16: 328 MB); hold one only while
    re-querying its frame. Filled by the first prediction that is given it; the frame's own inputs are not
    checked (give it the same x, m each time)."""

    def __init__(self, planes: list[np.ndarray] | None = None):
        self.planes = planes
        self.hidden: dict[tuple[int, int], np.ndarray] = {}   # (x0, x1) rows -> h (n, Dh)

    def hidden_slab(self, encoder, x0: int, x1: int) -> np.ndarray:
        """h of rows [x0, x1): sliced from a kept slab that covers them, else computed and kept."""
        row = encoder.grid.shape[1] * encoder.grid.shape[2]
        for (a, b), h in self.hidden.items():
            if a <= x0 and x1 <= b:
                return h[(x0 - a) * row:(x1 - a) * row]
        h = encoder.hidden_slab(self.planes, x0, x1)
        self.hidden[(x0, x1)] = h
        return h

    @property
    def nbytes(self) -> int:
        return sum(p.nbytes for p in self.planes or []) + sum(h.nbytes for h in self.hidden.values())


class VoxelClassifier:
    """An encoder's frames -> per-voxel decisions for a folded bank (see the module doc)."""

    def __init__(self, encoder):
        self.encoder = encoder

    def classify(self, x: np.ndarray, m: np.ndarray, folded: FoldedHeads,
                 identifier: Identifier = Identifier.MIN_ENTROPY, volumes: bool = False,
                 planes: list[np.ndarray] | None = None, features: FrameFeatures | None = None):
        """One frame's model inputs -> (out, timings): out = dict of (N,) arrays label (uint8), entropy,
        confidence, branch (+ unexplained, occupancy with volumes); timings: seconds in "encoder" (graphs and
        the numpy glue between them) and "heads" (class scores and the decision).

        planes: this frame's `encoder.plane_maps(x, m)` when the caller has them; features: a FrameFeatures of
        this frame, filled by the first call given it (later calls skip the planes and the decoder)."""
        identifier = Identifier(identifier)
        enc = self.encoder
        enc.check_folded(folded)
        n = enc.grid.num_voxels
        out = {"label": np.empty(n, np.uint8), "entropy": np.empty(n, np.float32),
               "confidence": np.empty(n, np.float32), "branch": np.empty(n, np.uint8)}
        if volumes:
            out["unexplained"] = np.empty(n, np.float32)
            out["occupancy"] = np.empty(n, np.float32)
        t_enc = t_heads = 0.0
        t = time.perf_counter()
        if features is not None:
            if features.planes is None:
                features.planes = planes if planes is not None else enc.plane_maps(x, m)
            planes = features.planes
        elif planes is None:
            planes = enc.plane_maps(x, m)
        row = enc.grid.shape[1] * enc.grid.shape[2]
        K = folded.num_classes
        for x0, x1 in enc.slabs(enc.slab_rows(folded.num_rows)):
            h = features.hidden_slab(enc, x0, x1) if features is not None else enc.hidden_slab(planes, x0, x1)
            s_main = enc.scores(folded.A[Branch.MAIN], h)
            t2 = time.perf_counter()
            z_main = folded.class_scores(s_main, Branch.MAIN)
            free = decision.main_free(z_main, K)
            need = decision.adapted_voxels(free, identifier, volumes)
            t3 = time.perf_counter()
            z_ad = None
            if len(need):
                h_need = h if len(need) == len(h) else h[need]      # need is sorted: all = arange(n)
                s_ad = enc.scores(folded.A[Branch.ADAPTED], enc.adapted_hidden(h_need))
            t4 = time.perf_counter()
            if len(need):
                z_ad = folded.class_scores(s_ad, Branch.ADAPTED)
            d = decision.decide(z_main, free, z_ad, need, identifier, K, folded.scales, volumes)
            sl = slice(x0 * row, x1 * row)
            out["label"][sl], out["entropy"][sl] = d.label, d.entropy
            out["confidence"][sl], out["branch"][sl] = d.confidence, d.branch
            if volumes:
                out["unexplained"][sl], out["occupancy"][sl] = d.unexplained, d.occupancy
            t5 = time.perf_counter()
            t_enc += (t2 - t) + (t4 - t3)
            t_heads += (t3 - t2) + (t5 - t4)
            t = t5
        return out, {"encoder": t_enc, "heads": t_heads}
