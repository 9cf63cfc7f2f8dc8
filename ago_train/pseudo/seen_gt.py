"""Seen-class GT mixed into pseudo-labels: the training labels of VEON's X/Y protocol (the paper's Tab. F).

In VEON's open-world benchmark X classes are *seen* (their GT annotations are used in training) and Y are
*unseen* (no annotations; only what the vision-language side gives). `mix_seen_gt` makes such labels from
an `ago pseudo-labels` folder and the dataset's Occ3D GT, per coarse (training-grid) voxel:

1. its GT block (the fine GT voxels it covers, e.g. 2x2x2 at 100x100x8 from 200x200x16) holds a seen
   class -> the seen class with the most GT voxels there (ties: the lower class index);
2. else, the pseudo-label calls it a seen class -> ignored (255): the annotations say no seen class is
   there, and they do not say what is;
3. else the pseudo-label stays (an unseen class, free, or unlabelled).

Free space stays the pseudo-labels' (the annotations are per class). 0 seen classes (X = 0) gives the
pseudo-labels unchanged. `write_seen_gt_folder` writes a new pseudo-label folder (meta.json says what was
mixed; the VLM embeddings are copied) that `ago train` reads like any other.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from ago_runtime.atomic import atomic_path, save_npz, write_text
from ago_runtime.classes import IGNORE
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.occ3d_waymo import load_ground_truth

from .generate import PseudoLabelDir, load_pseudo_labels, sample_dir


def mix_seen_gt(pseudo: np.ndarray, gt_classes: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """pseudo (X, Y, Z) uint8 class indices (free and 255 as stored); gt_classes (fX, fY, fZ) uint8 GT already
    mapped into the same class indices (LabelSpace.gt_lut: free and uncovered ids -> values >= K); seen (K,)
    bool -> the mixed (X, Y, Z) uint8 labels (rules in the module doc)."""
    X, Y, Z = pseudo.shape
    fx, fy, fz = (g // p for g, p in zip(gt_classes.shape, pseudo.shape))
    if (fx * X, fy * Y, fz * Z) != gt_classes.shape or min(fx, fy, fz) < 1:
        raise ValueError(f"GT shape {gt_classes.shape} is not a whole multiple of the pseudo-label grid {pseudo.shape}")
    K = len(seen)
    blocks = gt_classes.reshape(X, fx, Y, fy, Z, fz).transpose(0, 2, 4, 1, 3, 5).reshape(X, Y, Z, -1)
    best = np.zeros((X, Y, Z), np.int32)          # most GT voxels of one seen class in the block
    label = np.full((X, Y, Z), 255, np.int32)
    for k in np.flatnonzero(seen):
        count = (blocks == k).sum(-1)
        better = count > best                      # strict: ties keep the lower class index
        label[better] = k
        best[better] = count[better]
    out = pseudo.copy()
    has_seen = best > 0
    out[has_seen] = label[has_seen].astype(np.uint8)
    pseudo_seen = np.zeros(pseudo.shape, bool)
    in_space = pseudo < K
    pseudo_seen[in_space] = seen[pseudo[in_space]]
    out[pseudo_seen & ~has_seen] = IGNORE
    return out


def write_seen_gt_folder(ds, pseudo_dir: str | Path, out_dir: str | Path, label_space, indices: list[int],
                         progress=None) -> dict:
    """A new pseudo-label folder at out_dir: every sample of `indices` that pseudo_dir holds, with the seen
    classes (label_space.known) taken from the dataset's GT (mix_seen_gt). The label space must be the
    pseudo-labels' (same class names: a VEON prompt file differs from cw only in its @known list)."""
    src = PseudoLabelDir(pseudo_dir)
    out = Path(out_dir)
    if list(src.class_names) != list(label_space.class_names):
        raise AgoInputError(Path(pseudo_dir) / "meta.json", f"pseudo-labels use the classes {src.class_names}, the "
                            f"prompt file {label_space.source} has {label_space.class_names}")
    if ds.gts_root is None:
        raise AgoInputError(ds.root, "the dataset has no GT (gts/): seen classes need their annotations")
    seen = label_space.known_mask() if label_space.known else np.zeros(label_space.num_classes, bool)
    seen_names = [c for c, s in zip(label_space.class_names, seen) if s]
    lut = label_space.gt_lut()
    if out.exists() and (out / "meta.json").is_file():
        old = json.loads((out / "meta.json").read_text())
        if old.get("seen_gt", {}).get("seen") != seen_names or \
                old.get("seen_gt", {}).get("source") != str(Path(pseudo_dir).resolve()):
            raise AgoInputError(out / "meta.json", "this folder holds labels mixed with other seen classes or "
                                "from other pseudo-labels; use another --out or delete it")
    out.mkdir(parents=True, exist_ok=True)
    # meta.json first: a run killed half-way is resumed only with the same seen classes and source
    meta = dict(src.meta)
    meta["seen_gt"] = {"source": str(Path(pseudo_dir).resolve()),
                       "seen": seen_names,
                       "prompt_file": str(label_space.source),
                       "rule": "a coarse voxel whose GT block holds a seen class takes the most frequent one; "
                               "pseudo seen-class voxels without GT support ignored; the rest the pseudo-labels'"}
    write_text(out / "meta.json", json.dumps(meta, indent=1))
    shutil.copyfile(src.label_space_path, out / "label_space.txt")
    counts = {"samples": 0, "skipped": 0, "from_gt": 0, "ignored": 0, "voxels": 0, "seen": seen_names}
    todo = [i for i in indices if src.has(ds.scene_of(i), ds.sample_tokens[i])]
    it = progress(todo) if progress else todo
    for i in it:
        scene, token = ds.scene_of(i), ds.sample_tokens[i]
        d_out = sample_dir(out, scene, token)
        if (d_out / "labels.npz").is_file():
            counts["skipped"] += 1
            continue
        sem, ml, mc = load_pseudo_labels(pseudo_dir, scene, token)
        gt = load_ground_truth(ds.gt_file(i))[0].semantics   # either layout; ids of the label space's table
        mixed = mix_seen_gt(sem, lut[gt], seen)
        counts["from_gt"] += int(((mixed != sem) & (mixed != IGNORE)).sum())
        counts["ignored"] += int(((mixed == IGNORE) & (sem != IGNORE)).sum())
        counts["voxels"] += int(sem.size)
        emb = sample_dir(pseudo_dir, scene, token) / "embeds.npz"
        if emb.is_file():
            with atomic_path(d_out / "embeds.npz", suffix=".npz") as tmp:
                shutil.copyfile(emb, tmp)
        save_npz(d_out / "labels.npz", semantics=mixed, mask_lidar=ml, mask_camera=mc)   # last: marks it done
        counts["samples"] += 1
    return counts
