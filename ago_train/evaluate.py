"""Evaluation of a training checkpoint against Occ3D ground truth (`ago eval`).

Takes a checkpoint (checkpoint.py), a dataset root with GT, a split and a prompt file (default:
the checkpoint's own label space). For each frame: the model's voxel embeddings -> class logits
against the label space's text bank (class score = max over its phrases, plus free) -> labels
0..K-1 (class) / K (free) on the model grid -> nearest-upsampled to the GT grid when the model grid
is coarser -> `OccupancyMetric` over `mask_camera`, GT mapped into the label space with
`LabelSpace.gt_lut(free_index=K)` (Occ3D classes the space does not cover are ignored).

Identifier (`identifier`, ago_runtime.predict.contract.Identifier, the same choices as `ago infer`): NONE
classifies with F_3D only (the closed-world default, as the paper's supplementary material); MIN_ENTROPY /
MAX_CONF pick per voxel between F_3D and the adapted F~_3D (the open-world identifier; default when the
prompt file has unknown classes); ADAPTED takes F~_3D on every occupied voxel.

Writes `<out>/metrics.json` (the metric summary + known/unknown mIoU + run info) and
`<out>/metrics.md` (per-class IoU table).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ago_runtime.atomic import write_json, write_text
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.datasets import check_label_table
from ago_runtime.scoring.metric import OccupancyMetric, upsample_nearest
from ago_runtime.geometry.preprocess import Preprocess
from ago_runtime.predict.decision import Identifier
from ago_runtime.vocab.prompts import LabelSpace, parse_prompt_file

from .checkpoint import CheckpointContract
from .dataset import FrameList, OccSampleDataset, collate
from .distributed import pick_device

IDENTIFIERS = Identifier.names()   # `ago eval --identifier` choices: those of `ago infer`
READOUTS = ("model", "gt")   # the grid the planes are read on (evaluate)


def load_model(ckpt: CheckpointContract, device: torch.device, path: str | Path | None = None):
    """(ModelConfig, model in eval mode on `device`); AgoInputError naming `path` when the checkpoint's weights do
    not fit its model_config."""
    model = ckpt.build_model(str(path) if path is not None else "checkpoint")
    return ckpt.model_config, model.to(device)


def bank_for(ckpt: CheckpointContract, label_space: LabelSpace) -> tuple[torch.Tensor, torch.Tensor]:
    """(P, C) text embeddings and (P,) phrase classes of `label_space`: the checkpoint's own when it
    is the training label space (same phrases), else encoded with the torch MiniLM (same encoder hash), or with the
    CLIP folder the checkpoint was trained with (train_config text_encoder; same encoder id)."""
    saved, bank = ckpt.space, ckpt.bank
    if saved.phrases == label_space.phrases and saved.class_names == label_space.class_names:
        return bank.embeddings.float(), bank.phrase_class.long()
    from ago_runtime.vocab.bank import load_prompt_bank

    folder = ckpt.text_encoder
    if folder is not None:
        from ago_runtime.vocab.model_folder import check_same_encoder

        from .text.clip import TorchClipTextEncoder

        enc = TorchClipTextEncoder(folder, "the checkpoint's text_encoder")
        check_same_encoder("the checkpoint's prompt bank", bank.encoder_id, f"the CLIP folder {folder}",
                           enc.encoder_id)
        new = load_prompt_bank(label_space, enc)
        return torch.from_numpy(new.embeddings), torch.from_numpy(new.phrase_class)
    from .text.minilm import TorchMiniLMEncoder

    enc = TorchMiniLMEncoder()
    if enc.weights_hash != bank.encoder_hash:
        raise AgoInputError(None, f"the installed text encoder ({enc.weights_hash[:12]}) differs from the one "
                            f"the checkpoint was trained with ({bank.encoder_hash[:12]})")
    new = load_prompt_bank(label_space, enc)
    return torch.from_numpy(new.embeddings), torch.from_numpy(new.phrase_class)


def default_identifier(label_space: LabelSpace, trained_classes=None) -> Identifier:
    """MIN_ENTROPY when the label space has classes unknown to the model (outside its `@known:` list,
    or, without one, outside `trained_classes`), else NONE (closed world): the runtime's rule
    (ago_runtime.predict.heads.default_identifier), so `ago eval` and `ago infer` score alike."""
    from ago_runtime.predict.heads import default_identifier as rule

    trained = label_space.class_names if trained_classes is None else trained_classes
    return rule(label_space.class_names, label_space.known, trained)


@torch.no_grad()
def predict_labels(model, images: torch.Tensor, ego2img: torch.Tensor, text: torch.Tensor,
                   phrase_class: torch.Tensor, num_classes: int, identifier: Identifier,
                   scales: tuple[float, float] = (1.0, 1.0), adapted_stats: dict | None = None,
                   grid_shape: tuple[int, int, int] | None = None,
                   voxel_index: torch.Tensor | None = None) -> torch.Tensor:
    """(B, N) int64 labels on the model grid (or on `grid_shape`, the read-out grid): 0..K-1 class, K free.
    voxel_index (B, M) int64 flat indices into that grid: (B, M) labels of those voxels only (the same
    values as the full grid's at those indices: every step after the TPV planes is per voxel)."""
    from .model.text_logits import adapted_logits, class_logits, decide

    # F~_3D only when the identifier reads it
    identifier = Identifier(identifier)
    out = model(images, ego2img, voxel_index=voxel_index, adapted=identifier.reads_adapted, grid_shape=grid_shape)
    free = out.get("free_embedding", model.free_embedding)
    main = class_logits(out["feat"], text, phrase_class, num_classes, free, None, free_bias=out.get("free_bias"))
    adapted = (adapted_logits(out["feat_adapted"], text, phrase_class, num_classes, free, adapted_stats)
               if identifier.reads_adapted else None)
    return decide(main, adapted, identifier, num_classes, scales).label


def scored_subsets(label_space: LabelSpace) -> dict[str, list[str]]:
    """Known / unknown class subsets for mIoU (only classes with Occ3D ids are scored)."""
    known = set(label_space.known)
    scored = [c.name for c in label_space.classes if c.occ3d_ids]
    if not known or all(c in known for c in label_space.class_names):
        return {}
    return {"known": [c for c in scored if c in known], "unknown": [c for c in scored if c not in known]}


NO_GT_FIX = ("to score without Occ3D labels: `ago export` the checkpoint, `ago infer --images DATA --bundle B "
             "--out P`, then `ago metric --pred P --lidar DATA` (docs/metric_and_pictures.md)")


def check_has_gt(ds, indices: list[int], data) -> None:
    """Every frame to score has its ground-truth file (an Occ3D labels.npz, an Occ3D-Waymo _04.npz); otherwise one
    error naming the first missing file and the fix."""
    if ds.gts_root is None:
        raise AgoInputError(data, f"no Occ3D ground truth (no gts/ folder; --gts DIR names another); {NO_GT_FIX}")
    for i in indices:
        path = ds.gt_file(i)
        if not path.is_file():
            raise AgoInputError(path, f"no Occ3D ground truth for this frame; {NO_GT_FIX}")


def evaluate(ckpt_path: str | Path, data: str | Path, split: str = "val", prompts: str | None = None,
             identifier: str | None = None, out: str | Path | None = None, gts: str | None = None,
             max_frames: int | None = None, device: str = "auto", quiet: bool = False,
             readout: str = "model") -> dict:
    """Score a checkpoint; returns the results dict written to `<out>/metrics.json` (when `out`).

    readout: "model" predicts on the model's grid and repeats each voxel up to the GT grid (as the
    runtime's bundle does); "gt" reads the TPV planes directly at the GT grid's voxel centres (same
    weights, finer surfaces, 8x the voxels through the decoder at 100x100x8 -> 200x200x16;
    benchmarks/results/fine_query.md)."""
    from .sources import open_split

    if readout not in READOUTS:
        raise AgoInputError("--readout", f"must be one of {', '.join(READOUTS)}, got {readout!r}")
    if identifier is not None:
        identifier = Identifier.parse(identifier, "--identifier")
    dev = pick_device(device)
    ckpt = CheckpointContract.load(ckpt_path, map_location="cpu")
    mcfg, model = load_model(ckpt, dev, ckpt_path)
    label_space = parse_prompt_file(prompts) if prompts else ckpt.space
    K = label_space.num_classes
    identifier = identifier or default_identifier(label_space, ckpt.space.class_names)
    text, phrase_class = bank_for(ckpt, label_space)
    text, phrase_class = text.to(dev), phrase_class.to(dev)

    if max_frames is not None and (not isinstance(max_frames, int) or max_frames < 1):
        raise AgoInputError("--max-frames", f"must be >= 1 (or left out for every frame), got {max_frames!r}")
    ds, indices = open_split(data, gts, split)
    check_label_table(ds, label_space)   # GT ids and the label space's table agree (nuScenes / Occ3D-Waymo)
    if max_frames is not None:
        indices = indices[:max_frames]
    if not indices:
        raise AgoInputError(data, f"no frames in split {split!r}")
    check_has_gt(ds, indices, data)   # before any work
    grid = mcfg.grid_obj()
    pre = Preprocess(mcfg.image_width, mcfg.image_height)
    dataset = OccSampleDataset(FrameList(ds, indices), None, K, grid, pre,
                               gt_lut=label_space.gt_lut(free_index=K), with_gt=True,
                               camera_names=ckpt.camera_names)
    dataset.rig_of(ds[indices[0]])   # a frame of another rig is refused before any work
    names = list(label_space.class_names) + ["free"]
    metric = OccupancyMetric(names, free_index=K)
    loader = torch.utils.data.DataLoader(dataset, batch_size=1, shuffle=False, collate_fn=collate)
    from ago_runtime.progress import track

    iterator = loader if quiet else track(loader, description="eval", total=len(loader))
    for batch in iterator:   # batch_size 1
        gt, mask = batch["gt"][0], batch["gt_mask"][0]
        source = f"{batch['scene'][0]}/{batch['token'][0]}"
        shape = tuple(gt.shape) if readout == "gt" else tuple(grid.shape)
        # only the voxels the metric scores (mask_camera, ~1/3 of the grid) go through the decoder
        scored = np.flatnonzero(scored_voxels(np.asarray(mask, bool), shape, source))
        vol = np.full(int(np.prod(shape)), K, np.uint8)    # unscored voxels: free (the metric skips them)
        if scored.size:
            vol[scored] = predict_labels(model, batch["images"].to(dev), batch["ego2img"].to(dev), text,
                                         phrase_class, K, identifier, ckpt.scales,
                                         ckpt.adapted_stats, grid_shape=shape,
                                         voxel_index=torch.from_numpy(scored)[None].to(dev))[0].cpu().numpy()
        vol = _to_gt_resolution(vol.reshape(shape), gt.shape, source)
        metric.update(vol, gt, mask)

    subsets = scored_subsets(label_space)
    summary = metric.summary()
    result = {
        "checkpoint": str(ckpt_path), "data": str(data), "split": split, "frames": len(indices),
        "label_space": label_space.name, "prompt_file": str(label_space.source) if label_space.source else None,
        "identifier": identifier.value, "model_grid": list(grid.shape), "readout": readout,
        "mIoU": summary["mIoU"], "geometry_IoU": summary["geometry_IoU"],
        "subsets": {name: _pct(metric.miou(sub)) if sub else None for name, sub in subsets.items()},
        "metric": summary,
    }
    if out is not None:
        out = Path(out)
        write_json(out / "metrics.json", result)
        header = (f"# Evaluation: {Path(str(ckpt_path)).name} on {data} ({split}, {len(indices)} frames)\n\n"
                  f"Label space `{label_space.name}`, identifier `{identifier}`, model grid "
                  f"{grid.shape}, read out on the {'GT' if readout == 'gt' else 'model'} grid, scored over "
                  f"mask_camera at the GT resolution.\n\n")
        write_text(out / "metrics.md", header + metric.to_markdown({k: v for k, v in subsets.items() if v}))
    return result


def _pct(x: float) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x) * 100.0, 2)


def scored_voxels(mask: np.ndarray, shape: tuple, source: str) -> np.ndarray:
    """The GT's camera mask (at the GT resolution) -> a bool volume of `shape` (the prediction grid):
    a voxel is scored when any GT voxel it covers is (equal to `mask` when the shapes agree)."""
    if tuple(mask.shape) == tuple(shape):
        return mask
    (X, Y, Z), (fx, fy, fz) = shape, _grid_factors(mask.shape, shape, source)
    return mask.reshape(X, fx, Y, fy, Z, fz).any(axis=(1, 3, 5))


def _grid_factors(gt_shape: tuple, shape: tuple, source: str) -> tuple[int, int, int]:
    """Per axis how many GT voxels one voxel of `shape` covers (an AgoInputError unless whole numbers)."""
    factors = [g / v for g, v in zip(gt_shape, shape)]
    if any(f < 1 or abs(f - round(f)) > 1e-9 for f in factors):
        raise AgoInputError(source, f"GT grid {tuple(gt_shape)} is not an integer multiple of the model grid "
                            f"{tuple(shape)}")
    return tuple(int(round(f)) for f in factors)


def _to_gt_resolution(vol: np.ndarray, gt_shape: tuple, source: str) -> np.ndarray:
    if tuple(vol.shape) == tuple(gt_shape):
        return vol
    return upsample_nearest(vol, _grid_factors(gt_shape, vol.shape, source))
