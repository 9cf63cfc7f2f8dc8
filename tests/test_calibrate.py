"""The identifier's calibration (ago_train/calibrate.py) on hand-made cases: the scale fits, the
entropy match, and what it reads — training frames only, labelled voxels of training classes for the
scales, visible voxels (no labels) for the adapted statistics."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from ago_train.calibrate import best_scale, entropy_matched_scale, fit_scales


def _entropy(logits, s):
    p = torch.softmax(s * logits.double(), -1)
    return float(-(p * torch.log(p)).sum(-1).mean())


def test_best_scale_and_entropy_match_on_hand_made_logits():
    g = torch.Generator().manual_seed(0)
    target = torch.randint(0, 4, (2000,), generator=g)
    logits = torch.randn(2000, 4, generator=g)
    logits[torch.arange(2000), target] += 1.0          # right 60-70 % of the time
    s, nll = best_scale(logits, target)
    for other in (s * 0.8, s * 1.25):                   # a minimum of the NLL
        assert float(torch.nn.functional.cross_entropy(other * logits.double(), target)) > nll
    for h in (0.3, 0.9, 1.2):
        s_h = entropy_matched_scale(logits, h)
        assert abs(_entropy(logits, s_h) - h) < 1e-6
    assert entropy_matched_scale(logits, 10.0) == entropy_matched_scale(logits, 2 * np.log(4))  # clamped


class _Model(torch.nn.Module):
    """Features that are a fixed function of the voxel index (so the test knows which voxels were read)."""

    def __init__(self, C=8, N=50):
        super().__init__()
        g = torch.Generator().manual_seed(1)
        self.table = torch.randn(N, C, generator=g)
        self.table_ad = torch.randn(N, C, generator=g)
        self.free_embedding = torch.nn.Parameter(torch.randn(C, generator=g))
        self.read: list[torch.Tensor] = []

    def forward(self, images, ego2img, voxel_index, prefix=None, adapted=True):
        self.read.append(voxel_index[0].clone())
        return {"feat": self.table[voxel_index], "feat_adapted": self.table_ad[voxel_index],
                "free_embedding": self.free_embedding}


class _Dataset:
    def __init__(self, sem, align):
        self.sem, self.align, self.epoch, self.augment = sem, align, 0, "none"

    def __len__(self):
        return len(self.sem)

    def __getitem__(self, i):
        return {"ego2img": torch.zeros(6, 4, 4), "token": f"t{i}", "scene": "s", "semantics": self.sem[i],
                "e3d_index": self.align[i], "e3d_embeds": torch.zeros(len(self.align[i]), 8)}


def _trainer(sem, align, model):
    K = 3
    text = torch.nn.functional.normalize(torch.randn(4, 8, generator=torch.Generator().manual_seed(2)), dim=-1)
    return SimpleNamespace(model=model, info=SimpleNamespace(device=torch.device("cpu")),
                           label_space=SimpleNamespace(num_classes=K), cfg=SimpleNamespace(seed=0),
                           dataset=_Dataset(sem, align), text=text, phrase_class=torch.tensor([0, 1, 2, 2]))


def test_fit_scales_reads_only_labelled_training_voxels_and_visible_ones_for_statistics():
    N = 50
    sem = [torch.tensor(([0, 1, 2, 17, 255] * 10)[:N]) for _ in range(3)]   # 17 free, 255 unknown
    align = [torch.arange(0, N, 3) for _ in range(3)]                       # "visible occupied" voxels
    model = _Model(N=N)
    cal = fit_scales(_trainer(sem, align, model), max_frames=3, voxels_per_frame=1000)
    labelled = {int(v) for s in sem for v in torch.nonzero(s < 3).reshape(-1)}
    visible = {int(v) for a in align for v in a}
    read = {int(v) for r in model.read for v in r}
    assert read <= labelled | visible
    assert cal["adapted_voxels"] == sum(len(a) for a in align)
    np.testing.assert_allclose(cal["adapted_mean"].numpy(), model.table_ad[align[0]].mean(0).numpy(), atol=1e-5)
    # the scales do not change when free / unknown voxels' features change (they are never read)
    model2 = _Model(N=N)
    model2.table_ad = model.table_ad.clone()
    model2.table = model.table.clone()
    outside = torch.tensor(sorted(set(range(N)) - labelled - visible))
    model2.table[outside] = 100.0
    model2.table_ad[outside] = -100.0
    cal2 = fit_scales(_trainer(sem, align, model2), max_frames=3, voxels_per_frame=1000)
    assert cal2["scale_main"] == cal["scale_main"] and cal2["scale_adapted"] == cal["scale_adapted"]
    # the entropy-matched adapted scale gives the adapted branch the main branch's mean entropy
    assert cal["scale_adapted_entropy"] > 0 and cal["entropy_main"] > 0
