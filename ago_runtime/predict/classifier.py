"""`VoxelClassifier`: the slab loop, the one place where the encoder's features meet the voxel decision.

Data flows one way, slab by slab (n voxels of whole x-rows):

    planes (once a frame) -> h = the decoder's stages (every voxel) -> z_main = the main branch's class scores
    -> free = decision.main_free -> need = decision.adapted_voxels -> g = the adapter's stages on those voxels
    -> z_adapted -> decision.decide -> label, entropy, confidence, branch (+ occupancy, unexplained)

The encoder (ago_runtime.predict.encoder) only runs graphs, the folded heads (ago_runtime.predict.heads)
only hold the folded bank (data), and the rule is ago_runtime.predict.decision; this module is the rule's
only driver in the runtime (`ago infer`, `ago retrieve` through Predictor.predict_hidden, the export's parity
check; tests/test_architecture.py checks it). The whole grid's features never exist at once: memory follows
the slab.
"""

from __future__ import annotations

import time

import numpy as np

from ago_runtime.predict import decision
from ago_runtime.predict.decision import Branch, Identifier
from ago_runtime.predict.heads import SCORE_BUDGET_BYTES, FoldedHeads


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
        """h of rows [x0, x1): sliced from a kept slab that covers them, joined from kept slabs that cover them
        together (a re-query may cut the grid into other slabs: volumes use thinner ones), else computed and kept."""
        row = encoder.grid.shape[1] * encoder.grid.shape[2]
        parts, at = [], x0
        for (a, b), h in sorted(self.hidden.items()):  # a copy: slab workers may add slabs meanwhile
            if a <= at < b:
                end = min(b, x1)
                parts.append(h[(at - a) * row:(end - a) * row])
                at = end
                if at == x1:
                    return parts[0] if len(parts) == 1 else np.concatenate(parts)
        h = encoder.hidden_slab(self.planes, x0, x1)
        self.hidden[(x0, x1)] = h
        return h

    @property
    def nbytes(self) -> int:
        return sum(p.nbytes for p in self.planes or []) + sum(h.nbytes for h in self.hidden.values())


class VoxelClassifier:
    """Hidden features -> per-voxel decisions for a folded bank: the one driver of ago_runtime.predict.decision
    (see the module doc). `classify` runs an encoder's graphs on a frame, slab by slab (`ago infer`);
    `classify_hidden` takes the whole grid's h, g already computed (`ago retrieve`, benchmarks); `branch_labels`
    gives each branch's own argmax on every voxel (the export's parity check). All three decide a block of
    voxels in `decide_block`."""

    def __init__(self, encoder=None):
        self.encoder = encoder   # a SplitEncoder; None: classify_hidden only

    def classify(self, x: np.ndarray, m: np.ndarray, folded: FoldedHeads,
                 identifier: Identifier = Identifier.MIN_ENTROPY, volumes: bool = False,
                 planes: list[np.ndarray] | None = None, features: FrameFeatures | None = None):
        """One frame's model inputs -> (out, timings): out = dict of (N,) arrays label (uint8), entropy,
        confidence, branch (+ unexplained, occupancy with volumes); timings: seconds in "encoder" (graphs and
        the numpy glue between them) and "heads" (class scores and the decision); they add up to the call's wall
        time (slabs running in parallel, `SplitEncoder.map_slabs`, share it in the ratio of their own times).

        planes: this frame's `encoder.plane_maps(x, m)` when the caller has them; features: a FrameFeatures of
        this frame, filled by the first call given it (later calls skip the planes and the decoder)."""
        identifier = Identifier(identifier)
        enc = self.encoder
        enc.check_folded(folded)
        out = _outputs(enc.grid.num_voxels, volumes)
        t = time.perf_counter()
        if features is not None:
            if features.planes is None:
                features.planes = planes if planes is not None else enc.plane_maps(x, m)
            planes = features.planes
        elif planes is None:
            planes = enc.plane_maps(x, m)
        row = enc.grid.shape[1] * enc.grid.shape[2]

        def one_slab(x0: int, x1: int) -> tuple[float, float]:
            """Decide the slab's voxels into `out` -> (encoder s, heads s) of this slab."""
            t0 = time.perf_counter()
            h = features.hidden_slab(enc, x0, x1) if features is not None else enc.hidden_slab(planes, x0, x1)
            s_main = enc.scores(folded.A[Branch.MAIN], h)
            t2 = time.perf_counter()
            t_adapted = 0.0

            def adapted_scores(need: np.ndarray) -> np.ndarray:
                nonlocal t_adapted
                t_a = time.perf_counter()
                h_need = h if len(need) == len(h) else h[need]      # need is sorted: all = arange(n)
                s_ad = enc.scores(folded.A[Branch.ADAPTED], enc.adapted_hidden(h_need))
                t_adapted += time.perf_counter() - t_a
                return s_ad

            d = decide_block(folded, s_main, adapted_scores, identifier, volumes)
            _store(out, slice(x0 * row, x1 * row), d, volumes)
            t5 = time.perf_counter()
            return (t2 - t0) + t_adapted, (t5 - t2) - t_adapted

        t_planes = time.perf_counter() - t
        t = time.perf_counter()
        parts = enc.map_slabs(one_slab, list(enc.slabs(enc.slab_rows(folded.num_rows, volumes))))
        wall = time.perf_counter() - t
        # slabs may run in parallel: the loop's wall time is split in the ratio of the slabs' own encoder / heads time
        enc_s, heads_s = sum(p[0] for p in parts), sum(p[1] for p in parts)
        share = enc_s / (enc_s + heads_s) if enc_s + heads_s > 0 else 1.0
        return out, {"encoder": t_planes + wall * share, "heads": wall * (1.0 - share)}

    def classify_hidden(self, h: np.ndarray, g: np.ndarray, folded: FoldedHeads,
                        identifier: Identifier = Identifier.MIN_ENTROPY, volumes: bool = False,
                        chunk: int | None = None) -> dict[str, np.ndarray]:
        """The whole grid's hidden features h (N, Dh), g (N, Da) -> the dict of (N,) arrays `classify` gives,
        in chunks of `chunk` voxels (default: the score block within SCORE_BUDGET_BYTES, 8192..131072 voxels);
        the bank products in numpy."""
        identifier = Identifier(identifier)
        n = h.shape[0]
        if g.shape[0] != n:
            raise ValueError(f"h has {n} voxels but g has {g.shape[0]}")
        chunk = int(chunk or np.clip(SCORE_BUDGET_BYTES // (4 * folded.num_rows), 8192, 131072))
        out = _outputs(n, volumes)
        for start in range(0, n, chunk):
            sl = slice(start, min(n, start + chunk))
            g_sl = g[sl]
            d = decide_block(folded, folded.A[Branch.MAIN] @ h[sl].T,
                             lambda need: folded.A[Branch.ADAPTED] @ g_sl[need].T, identifier, volumes)
            _store(out, sl, d, volumes)
        return out

    def branch_labels(self, x: np.ndarray, m: np.ndarray, folded: FoldedHeads) -> dict[str, np.ndarray]:
        """Each branch's own label on every voxel, {"main": (N,), "adapted": (N,)}: the argmax of its class
        scores over [K_all classes + free] (no identifier, no scales), slab by slab."""
        enc = self.encoder
        enc.check_folded(folded)
        out: dict[str, list] = {branch.value: [] for branch in Branch}
        for _start, _stop, h, g in enc.chunks(x, m):
            for branch, feats in ((Branch.MAIN, h), (Branch.ADAPTED, g)):
                z = decision.class_scores(enc.scores(folded.A[branch], feats), folded.c[branch], folded.layout)
                out[branch.value].append(decision.softmax_stats(z).label)
        return {k: np.concatenate(v) for k, v in out.items()}


def decide_block(folded: FoldedHeads, s_main: np.ndarray, adapted_scores, identifier: Identifier,
                 volumes: bool) -> decision.Decision:
    """One block of n voxels: s_main (P+1, n) the main branch's scores A x^T (overwritten); adapted_scores(need)
    -> the adapted branch's scores (P+1, m) of the voxels `need` (sorted indices), asked for only when some
    voxel needs them."""
    K = folded.num_classes
    z_main = decision.class_scores(s_main, folded.c[Branch.MAIN], folded.layout)
    free = decision.main_free(z_main, K)
    need = decision.adapted_voxels(free, identifier, volumes)
    z_ad = None
    if len(need):
        z_ad = decision.class_scores(adapted_scores(need), folded.c[Branch.ADAPTED], folded.layout)
    return decision.decide(z_main, free, z_ad, need, identifier, K, folded.scales, volumes)


def _outputs(n: int, volumes: bool) -> dict[str, np.ndarray]:
    out = {"label": np.empty(n, np.uint8), "entropy": np.empty(n, np.float32),
           "confidence": np.empty(n, np.float32), "branch": np.empty(n, np.uint8)}
    if volumes:
        out["unexplained"] = np.empty(n, np.float32)
        out["occupancy"] = np.empty(n, np.float32)
    return out


def _store(out: dict[str, np.ndarray], sl: slice, d: decision.Decision, volumes: bool) -> None:
    out["label"][sl], out["entropy"][sl] = d.label, d.entropy
    out["confidence"][sl], out["branch"][sl] = d.confidence, d.branch
    if volumes:
        out["unexplained"][sl], out["occupancy"][sl] = d.unexplained, d.occupancy
