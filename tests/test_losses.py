"""Losses: Lovász-softmax, target conversion, grounding / occupancy / align, variants, overfitting."""

from __future__ import annotations

import itertools

import pytest
import torch

from ago_runtime.geometry.camera import Rig
from ago_runtime.classes import FREE, IGNORE
from ago_train.losses import BankTensors, LossConfig, compute_losses
from ago_train.losses.align import align_loss
from ago_train.losses.grounding import semantics_to_targets
from ago_train.losses.lovasz import lovasz_softmax
from ago_train.losses.occupancy import occupancy_binary, occupancy_loss
from ago_train.losses.sampling import select_stratified, select_training_voxels
from ago_train.model.config import ModelConfig


def _one_hot(pred: torch.Tensor, k: int) -> torch.Tensor:
    return torch.nn.functional.one_hot(pred, k).float()



@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Tiny tensors: one thread is faster than two and does not fight parallel test workers."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)

# ------------------------------------------------------------------ Lovász
def test_lovasz_is_zero_for_perfect_predictions():
    target = torch.tensor([0, 1, 2, 2, 1, 0, 2])
    assert float(lovasz_softmax(_one_hot(target, 3), target)) == pytest.approx(0.0, abs=1e-7)


def test_lovasz_matches_brute_force_jaccard_at_one_hot_predictions():
    """At one-hot probabilities the Lovász extension equals 1 - IoU; check every labelling of 5 voxels."""
    target = torch.tensor([0, 0, 1, 2, 1])
    for pred in itertools.product(range(3), repeat=5):
        pred = torch.tensor(pred)
        ious = []
        for c in range(3):
            inter = ((pred == c) & (target == c)).sum().item()
            union = ((pred == c) | (target == c)).sum().item()
            ious.append(inter / union)
        expected = 1.0 - sum(ious) / 3
        got = float(lovasz_softmax(_one_hot(pred, 3), target))
        assert got == pytest.approx(expected, abs=1e-6), (pred.tolist(), got, expected)


def test_weighted_lovasz_is_one_minus_weighted_iou_at_one_hot_predictions():
    """With voxel weights every Jaccard count becomes a sum of weights; all-ones weights change nothing."""
    target = torch.tensor([0, 0, 1, 2, 1, 2])
    weight = torch.tensor([0.5, 2.0, 1.0, 3.0, 0.25, 1.5])
    for pred in itertools.product(range(3), repeat=6):
        pred = torch.tensor(pred)
        ious = []
        for c in range(3):
            inter = float(weight[(pred == c) & (target == c)].sum())
            union = float(weight[(pred == c) | (target == c)].sum())
            ious.append(inter / union)
        got = float(lovasz_softmax(_one_hot(pred, 3), target, weight=weight))
        assert got == pytest.approx(1.0 - sum(ious) / 3, abs=1e-6), pred.tolist()
    soft = torch.softmax(torch.randn(6, 3), -1)
    assert float(lovasz_softmax(soft, target, weight=torch.ones(6))) == pytest.approx(float(lovasz_softmax(soft, target)))


def test_stratified_sample_draws_labelled_voxels_and_weights_restore_the_proportions():
    """The sample follows `occupied_share`; its weights give back the labelled grid's occupied share."""
    N = 20000
    sem = torch.full((1, N), IGNORE, dtype=torch.long)
    sem[0, :1000] = 3            # 1000 occupied
    sem[0, 1000:10000] = FREE    # 9000 free: the labelled grid is 10 % occupied
    gen = torch.Generator().manual_seed(0)
    for share in (0.25, 0.5, 0.75):
        idx, w = select_stratified(sem, 1000, share, generator=gen)
        assert idx.shape == w.shape == (1, 1000) and idx.unique().numel() == 1000
        labels = sem[0, idx[0]]
        assert not bool((labels == IGNORE).any())                          # unknown voxels are never drawn
        occ = labels != FREE
        assert int(occ.sum()) == round(1000 * share)                        # the drawn proportion
        assert float(w[0, occ].sum() / w.sum()) == pytest.approx(0.10, abs=1e-6)  # the weighted proportion
        assert float(w.mean()) == pytest.approx(1.0, abs=1e-6)
    # a frame with fewer occupied voxels than its share: the free stratum takes the rest of the slots
    idx, w = select_stratified(sem, 3000, 0.5, generator=gen)
    labels = sem[0, idx[0]]
    assert int((labels != FREE).sum()) == 1000 and float(w[0, labels != FREE].sum() / w.sum()) == pytest.approx(0.1)


def test_weighted_sample_losses_estimate_the_whole_labelled_grid():
    """Averaged over stratified samples, the weighted CE equals the CE over every labelled voxel."""
    cfg, model, images, ego2img, batch, bank = _setup(seed=3)
    model.eval()
    with torch.no_grad():
        full = compute_losses(model(images, ego2img), batch, bank, LossConfig(variant="grounding", use_noise=False))
        gen = torch.Generator().manual_seed(1)
        ce, occ = [], []
        for _ in range(40):
            idx, w = select_stratified(batch["semantics"], 200, 0.5, generator=gen)
            part = compute_losses(model(images, ego2img, voxel_index=idx), batch, bank,
                                  LossConfig(variant="grounding", use_noise=False), sample_weight=w)
            ce.append(float(part["grounding_ce"]))
            occ.append(float(part["occ"]))
    assert sum(ce) / len(ce) == pytest.approx(float(full["grounding_ce"]), rel=0.03)
    assert sum(occ) / len(occ) == pytest.approx(float(full["occ"]), rel=0.05)


def test_class_balance_weights_follow_the_rule():
    """Rare classes weigh more, the occupied classes keep their total mass (count-weighted mean 1), free
    weighs 1, the cap holds, an absent class gets the cap, alpha 0 is uniform."""
    import numpy as np

    from ago_train.losses.class_balance import CAP, class_balance_weights, count_classes

    sem = np.full((4, 4, 2), FREE, np.uint8)
    sem.reshape(-1)[:20] = 0          # 20 voxels of class 0
    sem.reshape(-1)[20:25] = 1        # 5 of class 1
    sem.reshape(-1)[25] = IGNORE
    counts = count_classes([sem, sem], 3)  # class 2 absent
    assert counts.tolist() == [40, 10, 0, 2 * (32 - 26)]
    w = class_balance_weights(counts, 0.5)
    assert w[-1] == 1.0 and w[2] == CAP
    assert w[1] / w[0] == pytest.approx(2.0, rel=1e-4)          # (40 / 10) ** 0.5
    assert (counts[:2] * w[:2]).sum() == pytest.approx(counts[:2].sum(), rel=1e-4)
    assert np.allclose(class_balance_weights(counts, 0.0), 1.0)
    steep = class_balance_weights([10000, 1, 50], 1.0)          # inverse frequency: the rare class capped
    assert steep[1] == pytest.approx(CAP) and steep[0] < steep[2] < CAP
    assert (np.array([10000, 1]) * steep[:2]).sum() == pytest.approx(10001, rel=1e-4)
    with pytest.raises(ValueError):
        class_balance_weights(counts, -1.0)
    with pytest.raises(ValueError):
        LossConfig(class_balance=3.0)


def test_class_weight_changes_only_the_cross_entropy():
    """class_weight reweights the CE's voxels by their target class; Lovász and occupancy stay as they were;
    all-ones weights change nothing."""
    cfg, model, images, ego2img, batch, bank = _setup(seed=5)
    model.eval()
    K = bank.num_classes
    with torch.no_grad():
        out = model(images, ego2img)
        plain = compute_losses(out, batch, bank, LossConfig(variant="grounding", use_noise=False))
        ones = compute_losses(out, batch, bank, LossConfig(variant="grounding", use_noise=False),
                              class_weight=torch.ones(K + 1))
        heavy_free = torch.ones(K + 1)
        heavy_free[K] = 5.0
        moved = compute_losses(out, batch, bank, LossConfig(variant="grounding", use_noise=False),
                               class_weight=heavy_free)
        # by hand: free voxels' CE counted 5 times in the weighted mean
        from ago_train.model.text_logits import class_logits

        logits = class_logits(out["feat"], bank.text, bank.phrase_class, K, out["free_embedding"], None)
        tgt = semantics_to_targets(batch["semantics"].reshape(-1), K)
        valid = tgt != IGNORE
        ce = torch.nn.functional.cross_entropy(logits.reshape(-1, logits.shape[-1])[valid], tgt[valid],
                                               reduction="none")
        wv = torch.where(tgt[valid] == K, 5.0, 1.0)
        expect = (ce * wv).sum() / wv.sum()
    assert float(ones["grounding_ce"]) == pytest.approx(float(plain["grounding_ce"]), rel=1e-5)
    assert float(moved["grounding_ce"]) == pytest.approx(float(expect), rel=1e-4)
    assert float(moved["grounding_ce"]) != pytest.approx(float(plain["grounding_ce"]), rel=1e-3)
    assert float(moved["grounding_lovasz"]) == pytest.approx(float(plain["grounding_lovasz"]), rel=1e-6)
    assert float(moved["occ"]) == pytest.approx(float(plain["occ"]), rel=1e-6)


def test_lovasz_ignore_and_present_classes():
    target = torch.tensor([0, 0, 1, IGNORE])
    prob = torch.tensor([[1.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])  # wrong only on the ignored voxel
    assert float(lovasz_softmax(prob, target)) == pytest.approx(0.0, abs=1e-7)
    # class 2 absent: counted only when only_present=False (its IoU is 0 -> loss 1 for that class)
    wrong = torch.tensor([[0.0, 0, 1.0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    present = float(lovasz_softmax(wrong, target))
    everyone = float(lovasz_softmax(wrong, target, only_present=False))
    assert present == pytest.approx(1 - (0.5 + 1.0) / 2)
    assert everyone == pytest.approx(1 - (0.5 + 1.0 + 0.0) / 3)
    soft = torch.softmax(torch.randn(6, 3, requires_grad=True), -1)
    lovasz_softmax(soft, torch.tensor([0, 1, 2, 0, 1, 2])).backward()   # differentiable


# ------------------------------------------------------------------ parts
def test_semantics_to_targets():
    sem = torch.tensor([0, 3, 4, FREE, IGNORE], dtype=torch.uint8)
    assert semantics_to_targets(sem, 4).tolist() == [0, 3, IGNORE, 4, IGNORE]


def test_occupancy_loss_uses_class_max_and_free():
    K = 2
    # columns: class0, class1, free, noise
    logits = torch.tensor([[10.0, -10.0, -10.0, 50.0], [-10.0, -10.0, 10.0, 50.0], [0.0, 0.0, 0.0, 0.0]])
    target = torch.tensor([1, K, IGNORE])
    assert float(occupancy_loss(logits, target, K)) < 1e-6            # noise column plays no part
    flipped = torch.tensor([K, 0, IGNORE])
    assert float(occupancy_loss(logits, flipped, K)) > 10


def test_align_losses():
    a = torch.randn(5, 8)
    assert float(align_loss(a, 3 * a, "cosine")) == pytest.approx(0.0, abs=1e-6)
    assert float(align_loss(a, -a, "cosine")) == pytest.approx(2.0, abs=1e-6)
    assert float(align_loss(a, a + 1, "mse")) == pytest.approx(1.0, abs=1e-6)
    assert float(align_loss(a, a - 2, "l1")) == pytest.approx(2.0, abs=1e-6)
    with pytest.raises(ValueError):
        align_loss(a, a, "huber")


# ------------------------------------------------------------------ compute_losses
def _setup(seed=0):
    torch.manual_seed(seed)
    cfg = ModelConfig.preset("tiny")
    model = cfg.build()
    X, Y, Z = cfg.grid_obj().shape
    images = torch.randn(1, 6, 3, cfg.image_height, cfg.image_width)
    ego2img = torch.from_numpy(Rig.nuscenes_like(cfg.image_width, cfg.image_height).ego2img())[None]
    # a structured scene: ground (class 0) at the bottom, a few boxes of classes 1..3, free above
    sem = torch.full((1, X, Y, Z), FREE, dtype=torch.uint8)
    sem[..., 0] = 0
    sem[0, 2:6, 3:7, 1:3] = 1
    sem[0, 12:15, 10:18, 1:3] = 2
    sem[0, 8:10, 1:4, 1] = 3
    sem[0, :, :2, 3] = IGNORE
    K, C = 4, cfg.embed_dim
    text = torch.nn.functional.normalize(torch.randn(7, C), dim=-1)
    bank = BankTensors(text, torch.tensor([0, 0, 1, 2, 3, 3, 3]), K, torch.nn.functional.normalize(torch.randn(3, C), dim=-1))
    occupied = torch.nonzero(sem.reshape(-1) < K).reshape(-1)
    batch = {"semantics": sem, "align_index": occupied, "align_embed": torch.randn(occupied.numel(), C)}
    return cfg, model, images, ego2img, batch, bank


def test_variants_and_gradient_routes():
    cfg, model, images, ego2img, batch, bank = _setup()
    expected = {"align": {"align", "occ"}, "grounding": {"grounding_ce", "grounding_lovasz", "occ"},
                "grounding+align": {"grounding_ce", "grounding_lovasz", "occ", "align"},
                "ago": {"grounding_ce", "grounding_lovasz", "occ", "align"}}
    for variant, keys in expected.items():
        model.zero_grad()
        losses = compute_losses(model(images, ego2img), batch, bank, LossConfig(variant=variant))
        assert set(losses) == keys | {"total"}
        assert all(torch.isfinite(v) for v in losses.values())
        losses["total"].backward()
        adapter_grad = model.adapter_out.weight.grad
        # only the paper's variant trains the adapter
        assert (adapter_grad is not None and adapter_grad.abs().sum() > 0) == (variant == "ago")
    off = compute_losses(model(images, ego2img), batch, bank, LossConfig(variant="grounding", use_occ=False))
    assert "occ" not in off
    align_only = compute_losses(model(images, ego2img), batch, bank, LossConfig(variant="align", use_occ=False))
    assert set(align_only) == {"align", "total"}
    no_noise = compute_losses(model(images, ego2img), batch, bank, LossConfig(variant="grounding", use_noise=False))
    with_noise = compute_losses(model(images, ego2img), batch, bank, LossConfig(variant="grounding"))
    assert float(no_noise["grounding_ce"].detach()) != float(with_noise["grounding_ce"].detach())
    with pytest.raises(ValueError):
        LossConfig(variant="everything")


def test_voxel_sample_losses_match_full_grid_when_sample_is_everything():
    cfg, model, images, ego2img, batch, bank = _setup()
    model.eval()
    N = model.num_voxels
    perm = torch.randperm(N)[None]
    with torch.no_grad():
        full = compute_losses(model(images, ego2img), batch, bank, LossConfig())
        part = compute_losses(model(images, ego2img, voxel_index=perm), batch, bank, LossConfig())
    for k in full:
        assert float(part[k]) == pytest.approx(float(full[k]), rel=1e-4, abs=1e-5), k
    some_align = batch["align_index"][::7]
    sample = select_training_voxels(batch["semantics"], 300, some_align)
    assert sample.shape == (1, 300) and sample.unique().numel() == 300
    assert set(some_align.tolist()) <= set(sample[0].tolist())            # align voxels come first
    labels = batch["semantics"].reshape(-1)[sample[0]]
    assert not bool((labels == IGNORE).any())                              # plenty of labelled voxels
    with torch.no_grad():
        sub = compute_losses(model(images, ego2img, voxel_index=sample), batch, bank, LossConfig())
    assert torch.isfinite(sub["total"]) and float(sub["align"]) > 0


def test_overfitting_one_batch_reduces_the_grounding_loss():
    cfg, model, images, ego2img, batch, bank = _setup(seed=1)
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=3e-3)
    first = last = None
    for step in range(50):
        losses = compute_losses(model(images, ego2img), batch, bank, LossConfig())
        grounding = float((losses["grounding_ce"] + losses["grounding_lovasz"]).detach())
        first = grounding if first is None else first
        last = grounding
        opt.zero_grad()
        losses["total"].backward()
        opt.step()
    assert last < 0.5 * first, (first, last)
    assert float(losses["align"].detach()) < 0.9


def test_hit_but_unlabelled_voxels_count_as_occupied_for_occupancy_only():
    """OCCUPIED_UNLABELLED (the LiDAR hit it, no mask named it): occupancy target 1, no grounding target."""
    from ago_runtime.classes import OCCUPIED_UNLABELLED

    sem = torch.tensor([0, 3, FREE, OCCUPIED_UNLABELLED, IGNORE])
    assert occupancy_binary(sem, 4).tolist() == [0, 0, 1, 0, IGNORE]
    assert semantics_to_targets(sem, 4).tolist() == [0, 3, 4, IGNORE, IGNORE]
    cfg, model, images, ego2img, batch, bank = _setup(seed=2)
    model.eval()
    marked = dict(batch)
    sem3 = batch["semantics"].clone()
    sem3[0, :, :2, 3] = OCCUPIED_UNLABELLED        # the unknown strip becomes "hit, unlabelled"
    marked["semantics"] = sem3
    with torch.no_grad():
        a = compute_losses(model(images, ego2img), batch, bank, LossConfig(variant="grounding"))
        b = compute_losses(model(images, ego2img), marked, bank, LossConfig(variant="grounding"))
    assert float(a["grounding_ce"]) == pytest.approx(float(b["grounding_ce"]))   # grounding ignores them
    assert float(a["occ"]) != pytest.approx(float(b["occ"]))                      # occupancy counts them


def test_unlabelled_uniform_loss_reads_only_hit_unlabelled_voxels_and_never_the_free_column():
    """loss.w_unlabelled_uniform: 0 at a uniform softmax over classes + noise words, grows as one column
    dominates, ignores labelled / free / unknown voxels and the free column, follows sample weights."""
    from ago_runtime.classes import OCCUPIED_UNLABELLED
    from ago_train.losses.total import unlabelled_uniform_loss

    K, Nn = 3, 4
    logits = torch.zeros(1, 4, K + 1 + Nn)
    sem = torch.tensor([[OCCUPIED_UNLABELLED, 0, FREE, IGNORE]])
    assert float(unlabelled_uniform_loss(logits, sem, K)) == pytest.approx(0.0, abs=1e-6)
    logits[0, 0, K] = 30.0                               # the free column: not part of the loss
    logits[0, 1:, 0] = 30.0                              # labelled, free, unknown voxels: not part of it
    assert float(unlabelled_uniform_loss(logits, sem, K)) == pytest.approx(0.0, abs=1e-6)
    logits[0, 0, 1] = 5.0                                # a class column dominates on the unlabelled voxel
    peaked = float(unlabelled_uniform_loss(logits, sem, K))
    logits[0, 0, 1] = 0.0
    logits[0, 0, K + 2] = 5.0                            # ... or a noise word does
    assert peaked > 0.5 and float(unlabelled_uniform_loss(logits, sem, K)) == pytest.approx(peaked, rel=1e-5)
    assert float(unlabelled_uniform_loss(logits, torch.tensor([[0, 0, FREE, IGNORE]]), K)) == 0.0
    # weighted mean over the selected voxels
    two = torch.zeros(1, 2, K + 1 + Nn)
    two[0, 0, 0] = 5.0
    sem2 = torch.tensor([[OCCUPIED_UNLABELLED, OCCUPIED_UNLABELLED]])
    one = float(unlabelled_uniform_loss(two[:, :1], sem2[:, :1], K))
    w = torch.tensor([[3.0, 1.0]])
    assert float(unlabelled_uniform_loss(two, sem2, K, w)) == pytest.approx(0.75 * one, rel=1e-5)
    # in compute_losses: off by default, on with a weight, and its gradient reaches F_3D
    cfg, model, images, ego2img, batch, bank = _setup(seed=3)
    marked = dict(batch)
    sem3 = batch["semantics"].clone()
    sem3[0, :, :2, 3] = OCCUPIED_UNLABELLED
    marked["semantics"] = sem3
    assert "unlabelled_uniform" not in compute_losses(model(images, ego2img), marked, bank, LossConfig())
    on = compute_losses(model(images, ego2img), marked, bank, LossConfig(w_unlabelled_uniform=0.5))
    assert float(on["unlabelled_uniform"]) > 0
    model.zero_grad()
    on["unlabelled_uniform"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())
    with pytest.raises(ValueError):
        LossConfig(w_unlabelled_uniform=-1.0)


def test_occupancy_weight_of_hit_but_unlabelled_voxels():
    """loss.occ_unlabelled_weight multiplies the occupancy loss's weight of OCCUPIED_UNLABELLED voxels
    only: equal losses at 1.0, a larger share for them above it, the other losses untouched."""
    from ago_runtime.classes import OCCUPIED_UNLABELLED

    cfg, model, images, ego2img, batch, bank = _setup(seed=4)
    model.eval()
    marked = dict(batch)
    sem = batch["semantics"].clone()
    sem[0, :, :2, 3] = OCCUPIED_UNLABELLED
    marked["semantics"] = sem
    with torch.no_grad():
        out = model(images, ego2img)
        base = compute_losses(out, marked, bank, LossConfig(variant="grounding"))
        same = compute_losses(out, marked, bank, LossConfig(variant="grounding", occ_unlabelled_weight=1.0))
        up = compute_losses(out, marked, bank, LossConfig(variant="grounding", occ_unlabelled_weight=4.0))
        plain = compute_losses(out, batch, bank, LossConfig(variant="grounding", occ_unlabelled_weight=4.0))
        plain1 = compute_losses(out, batch, bank, LossConfig(variant="grounding"))
    assert float(same["occ"]) == pytest.approx(float(base["occ"]))
    assert float(up["occ"]) != pytest.approx(float(base["occ"]))
    assert float(up["grounding_ce"]) == pytest.approx(float(base["grounding_ce"]))
    assert float(plain["occ"]) == pytest.approx(float(plain1["occ"]))     # no such voxel: no change
    # by hand: the weighted mean with the unlabelled voxels' weight x4
    from ago_train.losses.occupancy import occupancy_binary, occupancy_logits
    from ago_train.model.text_logits import class_logits
    K = bank.num_classes
    logits = class_logits(out["feat"], bank.text, bank.phrase_class, K, out["free_embedding"], bank.noise)[0]
    s = sem.reshape(-1)
    t = occupancy_binary(s, K)
    ce = torch.nn.functional.cross_entropy(occupancy_logits(logits, K), torch.where(t == IGNORE, 0, t),
                                           reduction="none")
    w = torch.where(t == IGNORE, 0.0, torch.where(s == OCCUPIED_UNLABELLED, 4.0, 1.0))
    assert float(up["occ"]) == pytest.approx(float((ce * w).sum() / w.sum()), rel=1e-4)
    with pytest.raises(ValueError):
        LossConfig(occ_unlabelled_weight=0.0)
