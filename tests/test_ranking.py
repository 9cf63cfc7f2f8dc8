"""Average precision and ROC AUC on hand-made rankings (ago_runtime/scoring/ranking.py)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from ago_runtime.scoring.ranking import average_precision, roc_auc


def test_average_precision_by_hand():
    # ranking: + - + - -  -> precisions at the positives 1/1 and 2/3 -> AP = (1 + 2/3) / 2
    s = np.array([5, 4, 3, 2, 1.0])
    y = np.array([1, 0, 1, 0, 0], bool)
    assert average_precision(s, y) == pytest.approx((1 + 2 / 3) / 2)
    assert average_precision(s, ~y) == pytest.approx((1 / 2 + 2 / 4 + 3 / 5) / 3)
    assert average_precision(-s, y) == pytest.approx((1 / 3 + 2 / 5) / 2)
    assert average_precision(np.arange(4.0), np.array([0, 0, 1, 1], bool)) == pytest.approx(1.0)
    # all tied: one threshold, precision = prevalence
    assert average_precision(np.zeros(10), np.arange(10) < 3) == pytest.approx(0.3)
    assert math.isnan(average_precision(s, np.zeros(5, bool)))


def test_random_rankings_score_the_prevalence():
    rng = np.random.default_rng(0)
    y = rng.random(20000) < 0.05
    aps = [average_precision(rng.random(20000), y) for _ in range(5)]
    assert np.mean(aps) == pytest.approx(y.mean(), abs=0.01)


def test_roc_auc_equals_the_pairwise_probability():
    rng = np.random.default_rng(1)
    s = rng.integers(0, 4, 30).astype(float)         # many ties
    y = rng.random(30) < 0.4
    pos, neg = s[y], s[~y]
    want = np.mean([(a > b) + 0.5 * (a == b) for a, b in itertools.product(pos, neg)])
    assert roc_auc(s, y) == pytest.approx(want)
    assert roc_auc(np.arange(6.0), np.arange(6) >= 3) == 1.0 and roc_auc(-np.arange(6.0), np.arange(6) >= 3) == 0.0
    assert math.isnan(roc_auc(s, np.ones(30, bool)))


def test_phrase_similarity_takes_each_voxels_branch_and_max_over_phrases():
    from ago_runtime.predict.heads import HeadWeights, phrase_similarity

    C = 3
    eye = np.eye(C, dtype=np.float32)
    heads = HeadWeights(W_dec=eye, b_dec=np.zeros(C, np.float32), W_ad=2 * eye, b_ad=np.zeros(C, np.float32),
                        free_embedding=np.zeros(C, np.float32))
    h = np.array([[1, 0, 0], [1, 0, 0]], np.float32)      # main branch points along x
    g = np.array([[0, 1, 0], [0, 1, 0]], np.float32)      # adapted branch along y
    branch = np.array([0, 1])
    one = phrase_similarity(heads, h, g, branch, np.array([1, 0, 0], np.float32))
    np.testing.assert_allclose(one, [1.0, 0.0], atol=1e-6)
    two = phrase_similarity(heads, h, g, branch, np.array([[1, 0, 0], [0, 3, 0]], np.float32))
    np.testing.assert_allclose(two, [1.0, 1.0], atol=1e-6)   # max over the two phrases, direction normalised
