"""The one prediction engine (ago_runtime.predict.classifier.VoxelClassifier) gives the labels the runtime gave
before it became the only driver of the decision.

tests/data/engine_labels_b3080d8.npz holds what the numpy heads gave at commit b3080d8 (`FoldedHeads.run`, the
path `ago retrieve` then took) on the exact inputs of `_case` (small integers and binary fractions: every score
is exact in float32, so no BLAS or CPU changes a bit), for every identifier. The encoder path (`classify`)
and the parity path (`branch_labels`) are compared with the same decision on the same slabs in
tests/test_runtime.py and tests/test_decision.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ago_runtime.predict import decision
from ago_runtime.predict.classifier import VoxelClassifier, decide_block
from ago_runtime.predict.decision import Branch, Identifier
from ago_runtime.predict.heads import FoldedHeads, HeadWeights

GOLDEN = Path(__file__).parent / "data" / "engine_labels_b3080d8.npz"


def _case():
    """(weights, phrase embeddings, phrase classes, K, h, g) of the golden file (do not change: the file holds
    what b3080d8 gave on exactly these)."""
    rng = np.random.default_rng(7)
    C, Dh, Da, K = 8, 6, 5, 4
    ints = lambda shape, lo, hi: rng.integers(lo, hi + 1, shape).astype(np.float32)  # noqa: E731
    w = HeadWeights(ints((C, Dh), -2, 2), ints(C, -1, 1), ints((C, Da), -2, 2), ints(C, -1, 1), ints(C, -1, 1),
                    branch_scales=np.array([1.5, 0.75], np.float32), free_bias=20.5)
    pc = np.array([2, 0, 1, 3, 0, 2, 1, 3, 3])
    emb = ints((len(pc), C), -1, 1)
    emb[np.abs(emb).sum(1) == 0, 0] = 1.0
    h = ints((1000, Dh), 0, 3)
    g = ints((1000, Da), 0, 3)
    return w, emb, pc, K, h, g


@pytest.mark.parametrize("identifier", list(Identifier))
def test_classify_hidden_gives_the_labels_of_before(identifier):
    golden = np.load(GOLDEN)
    w, emb, pc, K, h, g = _case()
    folded = FoldedHeads.fold(w, emb, pc, K)
    got = VoxelClassifier().classify_hidden(h, g, folded, identifier, chunk=300)
    for key in ("label", "branch", "entropy", "confidence"):
        np.testing.assert_array_equal(got[key], golden[f"{identifier.value}/{key}"], err_msg=key)
    label = got["label"]
    assert (label == K).any() and (label < K).any()                       # free and occupied voxels
    if identifier in (Identifier.MIN_ENTROPY, Identifier.MAX_CONF):
        assert got["branch"].any() and not got["branch"][label == K].any()


def test_chunks_and_blocks_decide_alike():
    """classify_hidden in any chunking, and one decide_block over every voxel, give the same outputs (the
    decision is per voxel); with volumes, the labels stay those without."""
    w, emb, pc, K, h, g = _case()
    folded = FoldedHeads.fold(w, emb, pc, K)
    engine = VoxelClassifier()
    for identifier in Identifier:
        a = engine.classify_hidden(h, g, folded, identifier, chunk=7)
        b = engine.classify_hidden(h, g, folded, identifier, volumes=True)
        whole = decide_block(folded, folded.A[Branch.MAIN] @ h.T, lambda need: folded.A[Branch.ADAPTED] @ g[need].T,
                             identifier, False)
        for key in ("label", "branch", "entropy", "confidence"):
            np.testing.assert_array_equal(a[key], getattr(whole, key))
            np.testing.assert_array_equal(a[key], b[key])
        assert {"unexplained", "occupancy"} <= set(b) and not {"unexplained", "occupancy"} & set(a)


def test_folded_heads_are_data():
    """A folded bank holds A, c, layout and scales; its class scores are decision.class_scores of them."""
    w, emb, pc, K, h, g = _case()
    folded = FoldedHeads.fold(w, emb, pc, K)
    assert folded.num_classes == K and folded.num_rows == len(pc) + 1 and folded.scales == (1.5, 0.75)
    assert folded.width(Branch.MAIN) == h.shape[1] and folded.width(Branch.ADAPTED) == g.shape[1]
    assert not any(hasattr(folded, name) for name in ("classify", "run", "class_scores", "A_main_T", "A_ad_T"))
    z = decision.class_scores(folded.A[Branch.MAIN] @ h.T, folded.c[Branch.MAIN], folded.layout)
    assert z.shape == (K + 1, len(h))
    with pytest.raises(ValueError, match="reference_classes"):
        FoldedHeads.fold(w, emb, pc, K, reference_classes=K)
