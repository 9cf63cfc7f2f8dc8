"""The adapted branch's phrase standardisation: torch (training/eval) and numpy (runtime) agree, the
runtime folds it exactly, a generic phrase stops winning everywhere, and bad statistics are refused."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from ago_runtime.errors import AgoInputError
from ago_runtime.predict.bundle import load_heads
from ago_runtime.predict.decision import phrase_standardisation as numpy_standardisation
from ago_runtime.predict.decision import Branch, class_scores, softmax_stats
from ago_runtime.predict.heads import FoldedHeads, HeadWeights
from ago_train.model.text_logits import adapted_logits, phrase_standardisation


WIDTHS = {"C": 16, "Dh": 10, "Da": 12}   # _heads' widths, as BundleContract.head_widths gives them


def _heads(rng, C=16, Dh=10, Da=12):
    return HeadWeights(rng.standard_normal((C, Dh)).astype(np.float32), rng.standard_normal(C).astype(np.float32),
                       rng.standard_normal((C, Da)).astype(np.float32), rng.standard_normal(C).astype(np.float32),
                       rng.standard_normal(C).astype(np.float32))


def _stats(rng, C=16):
    A = rng.standard_normal((C, C))
    return rng.standard_normal(C).astype(np.float32), (A @ A.T / C + 0.1 * np.eye(C)).astype(np.float32)


def test_torch_and_numpy_maps_agree():
    rng = np.random.default_rng(0)
    w = _heads(rng)
    w.adapted_mean, w.adapted_cov = _stats(rng)
    T = rng.standard_normal((7, 16)).astype(np.float32)
    scale, bias = numpy_standardisation(T, w.adapted_mean, w.adapted_cov)
    t_scaled, t_bias = phrase_standardisation(torch.from_numpy(T), torch.from_numpy(w.adapted_mean),
                                              torch.from_numpy(w.adapted_cov))
    np.testing.assert_allclose(t_scaled.numpy(), T * scale[:, None], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(t_bias.numpy(), bias, rtol=1e-5, atol=1e-6)
    # without statistics the map is the identity
    w.adapted_mean = w.adapted_cov = None
    s, b = numpy_standardisation(T, w.adapted_mean, w.adapted_cov)
    assert np.all(s == 1) and np.all(b == 0)


def test_folded_heads_apply_the_standardisation_exactly():
    rng = np.random.default_rng(1)
    w = _heads(rng)
    w.adapted_mean, w.adapted_cov = _stats(rng)
    K, P = 4, 9
    pc = np.array([2, 0, 1, 3, 0, 2, 1, 3, 3])
    emb = rng.standard_normal((P, 16)).astype(np.float32)
    g = rng.standard_normal((500, 12)).astype(np.float32)
    fh = FoldedHeads.fold(w, emb, pc, K)
    feat_ad = g.astype(np.float64) @ w.W_ad.T.astype(np.float64) + w.b_ad
    t = emb.astype(np.float64)
    sd = np.sqrt(np.einsum("pc,cd,pd->p", t, w.adapted_cov.astype(np.float64), t))
    z = (feat_ad @ t.T - t @ w.adapted_mean.astype(np.float64)) / sd
    want = np.stack([z[:, pc == k].max(1) for k in range(K)], axis=1)
    got = class_scores(fh.A[Branch.ADAPTED] @ g.T, fh.c[Branch.ADAPTED], fh.layout).T    # (n, K + 1)
    np.testing.assert_allclose(got[:, :K], want, rtol=1e-4, atol=1e-4)
    # the torch path of training and evaluation gives the same class logits
    logits = adapted_logits(torch.from_numpy(feat_ad.astype(np.float32))[None], torch.from_numpy(emb),
                            torch.from_numpy(pc), K, torch.from_numpy(w.free_embedding),
                            {"adapted_mean": torch.from_numpy(w.adapted_mean),
                             "adapted_cov": torch.from_numpy(w.adapted_cov)})[0]
    np.testing.assert_allclose(logits[:, :K].numpy(), want, rtol=1e-4, atol=1e-4)


def test_a_generic_phrase_stops_winning_everywhere():
    """Voxels = a shared offset along phrase 0's direction + a small class direction. Raw dot products
    give phrase 0 (the 'generic' one) every voxel; standardised scores recover each voxel's class."""
    rng = np.random.default_rng(2)
    C, K, n = 8, 3, 600
    T = np.eye(K, C)
    T[0] = np.ones(C) / np.sqrt(C)           # phrase 0 points along the shared offset
    T[1:, :] = np.eye(K, C)[1:] * 0.8 + T[0] * 0.6
    y = rng.integers(0, K, n)
    x = 4.0 * T[0] + 0.6 * T[y] + 0.05 * rng.standard_normal((n, C))
    raw = x @ T.T
    assert (raw.argmax(1) == 0).mean() > 0.95
    stats = {"adapted_mean": torch.tensor(x.mean(0)), "adapted_cov": torch.tensor(np.cov(x, rowvar=False))}
    z = adapted_logits(torch.tensor(x)[None], torch.tensor(T), torch.arange(K), K, torch.zeros(C), stats)[0, :, :K]
    assert (z.argmax(1).numpy() == y).mean() > 0.9


def test_bundle_heads_refuse_bad_statistics(tmp_path):
    rng = np.random.default_rng(3)
    w = _heads(rng)
    w.adapted_mean, w.adapted_cov = _stats(rng)
    good = tmp_path / "heads.npz"
    np.savez(good, **w.to_arrays())
    back = load_heads(good, WIDTHS)
    np.testing.assert_array_equal(back.adapted_cov, w.adapted_cov)
    arrays = w.to_arrays()
    for damage in ({"adapted_cov": arrays["adapted_cov"][:3]}, {"adapted_mean": np.full(16, np.nan, np.float32)}):
        bad = tmp_path / "bad.npz"
        np.savez(bad, **{**arrays, **damage})
        with pytest.raises(AgoInputError, match="adapted"):
            load_heads(bad, WIDTHS)


def test_export_parity_reference_standardises_like_the_runtime():
    """ago_export.parity's unfolded float64 reference applies the same map as the folded runtime heads."""
    from types import SimpleNamespace

    from ago_export.parity import reference_labels

    rng = np.random.default_rng(4)
    w = _heads(rng)
    w.adapted_mean, w.adapted_cov = _stats(rng)
    K, P = 4, 6
    pc = np.array([0, 1, 2, 3, 1, 2])
    emb = rng.standard_normal((P, 16)).astype(np.float32)
    bank = SimpleNamespace(embeddings=emb, phrase_class=pc, num_classes=K)
    g = rng.standard_normal((400, 12)).astype(np.float32)
    h = rng.standard_normal((400, 10)).astype(np.float32)
    feat = h.astype(np.float64) @ w.W_dec.T + w.b_dec
    feat_ad = g.astype(np.float64) @ w.W_ad.T + w.b_ad
    ref = reference_labels(feat, feat_ad, bank, w)
    fh = FoldedHeads.fold(w, emb, pc, K)
    got = softmax_stats(class_scores(fh.A[Branch.ADAPTED] @ g.T, fh.c[Branch.ADAPTED], fh.layout)).label
    assert np.mean(got == ref["adapted"]) > 0.995
    plain = reference_labels(feat, feat_ad, bank, dataclasses.replace(w, adapted_mean=None, adapted_cov=None))
    assert np.mean(plain["adapted"] != ref["adapted"]) > 0.05   # the map does change the labels
