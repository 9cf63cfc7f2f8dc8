"""Score one checkpoint several ways from ONE forward pass per frame (the experiments' evaluator).

`ago eval` (evaluate.py) scores a checkpoint one way. The experiments need the same checkpoint
scored under several label spaces and identifiers (Tab. 2 and 4 of the paper, the closed-world
classifier baseline) and a few statistics for the figures; running the encoder once per frame
and scoring every `View` from its output costs one eval instead of five.

A `View` is (prompt file, identifier, closed_set):
- identifier (ago_runtime.predict.decision.Identifier): NONE (F_3D only), MAX_CONF / MIN_ENTROPY (the
  open-world identifier between F_3D and the adapted F~_3D, ago_train.model.text_logits.decide)
  or ADAPTED (F~_3D only);
- closed_set=True drops the phrases of the label space's unknown classes, so they can never be
  predicted: a closed-world classifier over the known classes (the SelfOcc-like baseline);
- adapted_scale multiplies the adapted branch's logits before its softmax (a diagnostic: the adapted
  embeddings are trained with a cosine loss, so their length, and with it the sharpness of P~, is not
  learnt; see docs/results.md, Tab. 4).

Scoring is evaluate.py's: labels on the model grid -> nearest-upsampled to the GT grid -> Occ3D
metric over mask_camera with the GT mapped into the view's label space.

Statistics (`stats_view`, one label space): per GT class, the mean entropy of P (F_3D) and P~ (F~_3D)
over the class's visible voxels, and the mean cosine similarity of F_3D / F~_3D to every class text
(the modality-gap heatmap). These are taken on the model grid with the GT decimated to it (the GT
label of each model voxel's first sub-voxel), which is exact when the grids agree.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ago_runtime.scoring.metric import OccupancyMetric
from ago_runtime.geometry.preprocess import Preprocess
from ago_runtime.vocab.prompts import LabelSpace, parse_prompt_file

from ..checkpoint import CheckpointContract
from ..dataset import FrameList, OccSampleDataset, collate
from ..evaluate import _pct, _to_gt_resolution, bank_for, load_model, scored_subsets, scored_voxels
from ..model.text_logits import adapted_logits, class_logits, decide
from ago_runtime.predict.decision import Identifier

@dataclass(frozen=True)
class View:
    name: str
    prompts: str                 # prompt file path
    identifier: Identifier = Identifier.NONE
    closed_set: bool = False
    adapted_scale: float = 1.0   # multiplies the adapted branch's logits (a temperature; 1 = the model's own)

    def __post_init__(self):
        try:
            object.__setattr__(self, "identifier", Identifier(self.identifier))
        except ValueError:
            raise ValueError(f"view {self.name}: unknown identifier {self.identifier!r}") from None


@dataclass
class _Bank:
    space: LabelSpace
    text: torch.Tensor           # (P, C)
    phrase_class: torch.Tensor   # (P,)
    class_text: torch.Tensor     # (K, C) normalised mean phrase embedding per class


def _bank(ckpt: CheckpointContract, prompts: str, closed_set: bool) -> _Bank:
    space = parse_prompt_file(prompts)
    text, pc = bank_for(ckpt, space)
    K = space.num_classes
    class_text = torch.stack([text[pc == k].mean(0) for k in range(K)])
    class_text = class_text / class_text.norm(dim=-1, keepdim=True)
    if closed_set:
        keep = torch.as_tensor(space.known_mask())[pc]
        text, pc = text[keep], pc[keep]
    return _Bank(space, text.float(), pc.long(), class_text.float())


def _decimate(vol: np.ndarray, shape: tuple) -> np.ndarray:
    f = [g // m for g, m in zip(vol.shape, shape)]
    return vol[:: f[0], :: f[1], :: f[2]][: shape[0], : shape[1], : shape[2]]


class _Stats:
    """Per GT class sums of entropies and of cosine similarities to every class text."""

    def __init__(self, K: int):
        self.K = K
        self.count = np.zeros(K, np.int64)
        self.h_main = np.zeros(K)
        self.h_adap = np.zeros(K)
        self.sim_main = np.zeros((K, K))
        self.sim_adap = np.zeros((K, K))

    def update(self, gt_model: np.ndarray, mask_model: np.ndarray, h_main, h_adap, s_main, s_adap):
        g = gt_model.reshape(-1)
        m = mask_model.reshape(-1).astype(bool) & (g < self.K)
        g = g[m]
        self.count += np.bincount(g, minlength=self.K)[: self.K]
        self.h_main += np.bincount(g, weights=h_main[m], minlength=self.K)[: self.K]
        self.h_adap += np.bincount(g, weights=h_adap[m], minlength=self.K)[: self.K]
        for k in range(self.K):
            self.sim_main[:, k] += np.bincount(g, weights=s_main[m, k], minlength=self.K)[: self.K]
            self.sim_adap[:, k] += np.bincount(g, weights=s_adap[m, k], minlength=self.K)[: self.K]

    def result(self, space: LabelSpace) -> dict:
        n = np.maximum(self.count, 1)

        def rnd(a):
            return np.round(a, 4).tolist()

        return {"classes": list(space.class_names), "known": sorted(space.known), "voxels": self.count.tolist(),
                "entropy_main": rnd(self.h_main / n), "entropy_adapted": rnd(self.h_adap / n),
                "cos_main": rnd(self.sim_main / n[:, None]), "cos_adapted": rnd(self.sim_adap / n[:, None])}


@torch.no_grad()
def evaluate_views(ckpt_path: str | Path, data: str | Path, views: list[View], split: str = "val",
                   gts: str | None = None, max_frames: int | None = None, stats_view: str | None = None,
                   keep_frames: int = 0, quiet: bool = True) -> dict:
    """{"views": {name: result}, "stats": {...} | None, "kept": {name: [(scene, token, labels (X,Y,Z) uint8)]}}.

    A result has evaluate.py's keys: mIoU, mIoU_star, geometry_IoU, subsets (known/unknown mIoU), metric."""
    from ago_runtime.progress import track

    from ..sources import open_split

    dev = torch.device("cpu")
    ckpt = CheckpointContract.load(ckpt_path, map_location="cpu")
    mcfg, model = load_model(ckpt, dev, ckpt_path)
    scales = ckpt.scales
    adapted_stats = ckpt.adapted_stats
    banks = {v.name: _bank(ckpt, v.prompts, v.closed_set) for v in views}
    ds, indices = open_split(data, gts, split)
    if max_frames is not None:
        indices = indices[:max_frames]
    grid = mcfg.grid_obj()
    pre = Preprocess(mcfg.image_width, mcfg.image_height)
    # GT is loaded once (in the Occ3D ids) and mapped into each view's label space here
    dataset = OccSampleDataset(FrameList(ds, indices), None, 17, grid, pre, gt_lut=np.arange(256, dtype=np.uint8),
                               with_gt=True,
                               camera_names=ckpt.camera_names)
    dataset.rig_of(ds[indices[0]])   # a frame of another rig is refused before any work
    metrics = {v.name: OccupancyMetric(list(banks[v.name].space.class_names) + ["free"],
                                       free_index=banks[v.name].space.num_classes) for v in views}
    luts = {v.name: banks[v.name].space.gt_lut(free_index=banks[v.name].space.num_classes) for v in views}
    stats = _Stats(banks[stats_view].space.num_classes) if stats_view else None
    kept: dict[str, list] = {v.name: [] for v in views}
    loader = torch.utils.data.DataLoader(dataset, batch_size=1, shuffle=False, collate_fn=collate)
    it = loader if quiet else track(loader, description=f"eval {Path(str(ckpt_path)).parent.name}",
                                    total=len(loader))
    num_voxels = int(np.prod(grid.shape))
    for n_frame, batch in enumerate(it):
        gt_occ = np.asarray(batch["gt"][0]).astype(np.uint8)
        mask = np.asarray(batch["gt_mask"][0])
        # the decoder runs on the voxels the metric scores (as `ago eval`), except for the frames kept for
        # pictures, which need every voxel; per voxel the labels are those of a whole-grid pass
        sel = None
        if n_frame >= keep_frames:
            sel = np.flatnonzero(scored_voxels(mask.astype(bool), tuple(grid.shape), str(batch["token"][0])))
            sel = sel if sel.size else None
        out = model(batch["images"], batch["ego2img"],
                    voxel_index=None if sel is None else torch.from_numpy(sel)[None])
        free = out.get("free_embedding", model.free_embedding)

        def on_grid(a: np.ndarray, fill) -> np.ndarray:
            """Per decoded voxel values -> the whole model grid (C order), `fill` elsewhere."""
            if sel is None:
                return a
            full = np.full((num_voxels,) + a.shape[1:], fill, a.dtype)
            full[sel] = a
            return full

        for v in views:
            b = banks[v.name]
            K = b.space.num_classes
            main = class_logits(out["feat"], b.text, b.phrase_class, K, free, None, free_bias=out.get("free_bias"))[0]
            adapted = (adapted_logits(out["feat_adapted"], b.text, b.phrase_class, K, free, adapted_stats)[0]
                       * v.adapted_scale
                       if v.identifier.reads_adapted or v.name == stats_view else None)
            d = decide(main, adapted, v.identifier, K, scales)
            labels = on_grid(d.label.numpy().astype(np.uint8), K)
            labels = labels.reshape(grid.shape)
            gt = luts[v.name][gt_occ]
            metrics[v.name].update(_to_gt_resolution(labels, gt.shape, str(batch["token"][0])), gt, mask)
            if n_frame < keep_frames:
                kept[v.name].append((batch["scene"][0], batch["token"][0], labels))
            if v.name == stats_view:
                # the identifier's class entropies (calibrated, over the K classes), as the decision took them
                h_main, h_adap = d.entropy_main.numpy(), d.entropy_adapted.numpy()
                f = torch.nn.functional.normalize(out["feat"][0], dim=-1)
                fa = torch.nn.functional.normalize(out["feat_adapted"][0], dim=-1)
                # the decimated mask's voxels (first sub-voxel) are among the decoded ones
                stats.update(_decimate(gt, grid.shape), _decimate(mask, grid.shape), on_grid(h_main, 0.0),
                             on_grid(h_adap, 0.0), on_grid((f @ b.class_text.T).numpy(), 0.0),
                             on_grid((fa @ b.class_text.T).numpy(), 0.0))
    results = {}
    for v in views:
        m, space = metrics[v.name], banks[v.name].space
        subsets = scored_subsets(space)
        summary = m.summary()
        results[v.name] = {
            "checkpoint": str(ckpt_path), "split": split, "frames": len(indices), "label_space": space.name,
            "identifier": v.identifier.value, "closed_set": v.closed_set,
            "mIoU": summary["mIoU"], "mIoU_star": _pct(m.miou_star()), "geometry_IoU": summary["geometry_IoU"],
            "subsets": {name: _pct(m.miou(sub)) if sub else None for name, sub in subsets.items()},
            "metric": summary,
        }
    return {"views": results, "stats": stats.result(banks[stats_view].space) if stats else None, "kept": kept}
