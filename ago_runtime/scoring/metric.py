"""The Occ3D occupancy metric: a confusion matrix accumulated over a whole split.

Takes predicted and ground-truth semantic volumes (any equal shape, integer labels, usually
(200, 200, 16) uint8 in Occ3D's [x, y, z] order) and a visibility mask; gives per-class IoU,
mIoU (several class subsets) and geometry IoU. Same semantics as the Occ3D challenge's
`Metric_mIoU` with `use_image_mask=True`:

- only voxels where `mask_camera` is set count. The mask is converted to **bool** before use: a
  uint8 0/1 mask used as an index would pick voxels 0 and 1 over and over instead of masking;
- GT voxels labelled 255 (unknown) are skipped, like the official `(gt >= 0) & (gt < n)` filter;
- one (K+1) x (K+1) confusion matrix (rows = GT, columns = prediction) is summed over all frames,
  with `free` as a full row and column (a class voxel predicted free is a false negative of that
  class and a false positive of free), and IoUs are computed once from the sum (not averaged per
  frame);
- IoU_c = TP / (TP + FP + FN) = diag / (row + col - diag);
- mIoU = nanmean of the IoUs of the semantic classes (for Occ3D: 0..16, free excluded).

Absent classes: a class that never appears in GT nor in predictions has row + col == 0, so
its IoU is 0/0 = NaN (never 1) and `nanmean` leaves it out of every mean; the official code's
`np.nanmean` behaves the same way. A class present in GT but never predicted scores 0, and a class
only predicted (false positives) scores 0 too.

Resolution: evaluation always happens at the GT resolution. A prediction made on a coarser grid
(e.g. 100 x 100 x 16) must first be brought up with `upsample_nearest(pred, (2, 2, 1))`.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.classes import FREE, IGNORE, MIOU_STAR_EXCLUDED, OCC3D_CLASSES, ClassTable
from ago_runtime.volumes import upsample_nearest  # also imported from here by metric's callers


def _pct(x: float) -> float | None:
    """A ratio as a percentage rounded to 2 decimals; NaN -> None (JSON has no NaN)."""
    return None if x is None or not np.isfinite(x) else round(float(x) * 100.0, 2)


def to_gt_resolution(pred: np.ndarray, gt_shape: tuple[int, ...], path: Path) -> np.ndarray:
    """Upsample a coarser prediction by an integer factor per axis; refuse any other shape."""
    if pred.shape == tuple(gt_shape):
        return pred
    factors = [g // p if p and g % p == 0 else 0 for g, p in zip(gt_shape, pred.shape)]
    if 0 in factors:
        raise AgoInputError(path, f"prediction shape {pred.shape} is not the GT shape {tuple(gt_shape)} "
                                  "nor an integer fraction of it")
    return upsample_nearest(pred, factors)


class OccupancyMetric:
    """Confusion-matrix occupancy metric over a label space of named classes plus one `free` id.

    `class_names` lists every label id in order, free included (Occ3D: 17 classes + "free" at 17).
    Labels must lie in 0..len(class_names)-1; GT 255 is ignored.

    `table` (a `ClassTable`, e.g. `OCC3D_WAYMO`) replaces `class_names` / `free_index` / `ignore_index`:
    labels are then given as the table's file ids (Occ3D-Waymo: free = 23) and are brought to the
    table's dense order (classes, then free) before counting; a value the table does not name is a
    ValueError. With the Occ3D-nuScenes table the ids already are the dense order, so nothing changes.
    """

    def __init__(self, class_names: Sequence[str] = OCC3D_CLASSES, free_index: int = FREE,
                 ignore_index: int = IGNORE, table: ClassTable | None = None):
        self.table = table
        if table is not None:
            class_names, free_index, ignore_index = table.label_names, table.free_index, IGNORE
        self.class_names = list(class_names)
        self.num_labels = len(self.class_names)
        if not 0 <= free_index < self.num_labels:
            raise ValueError(f"free_index {free_index} outside 0..{self.num_labels - 1}")
        if len(set(self.class_names)) != self.num_labels:
            raise ValueError("class names must be unique")
        if 0 <= ignore_index < self.num_labels:
            raise ValueError(f"ignore_index {ignore_index} collides with a class id")
        self.free_index = int(free_index)
        self.ignore_index = int(ignore_index)
        self.confusion = np.zeros((self.num_labels, self.num_labels), dtype=np.int64)  # rows GT, cols pred
        self.frames = 0

    # ---- accumulation -------------------------------------------------------------------------
    def update(self, pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> None:
        """Add one frame (or a batch: any equal shapes). `mask` (bool or 0/1) selects the voxels that count."""
        pred = np.asarray(pred)
        gt = np.asarray(gt)
        if self.table is not None and not self.table.is_dense:
            pred = self.table.to_dense(pred, "prediction labels")
            gt = self.table.to_dense(gt, "GT labels")
        if pred.shape != gt.shape:
            raise ValueError(f"prediction shape {pred.shape} != GT shape {gt.shape} "
                             "(evaluate at GT resolution: see upsample_nearest)")
        keep = gt != self.ignore_index
        if mask is not None:
            mask = np.asarray(mask)
            if mask.shape != gt.shape:
                raise ValueError(f"mask shape {mask.shape} != GT shape {gt.shape}")
            keep &= mask.astype(bool)  # NEVER index with a uint8 mask
        g = gt[keep].astype(np.int64)
        p = pred[keep].astype(np.int64)
        n = self.num_labels
        for what, a in (("GT", g), ("prediction", p)):
            if a.size and (a.min() < 0 or a.max() >= n):
                raise ValueError(f"{what} labels must lie in 0..{n - 1} (GT may also be {self.ignore_index}); "
                                 f"found {int(a.min())}..{int(a.max())}")
        self.confusion += np.bincount(g * n + p, minlength=n * n).reshape(n, n)
        self.frames += 1

    def merge(self, other: "OccupancyMetric") -> "OccupancyMetric":
        """Add another metric's counts (e.g. from another process); returns self."""
        if other.class_names != self.class_names or other.free_index != self.free_index:
            raise ValueError("can only merge metrics over the same label space")
        self.confusion += other.confusion
        self.frames += other.frames
        return self

    def reset(self) -> None:
        self.confusion[:] = 0
        self.frames = 0

    # ---- results ------------------------------------------------------------------------------
    @property
    def semantic_names(self) -> list[str]:
        """All class names except free (the classes mIoU averages over)."""
        return [c for i, c in enumerate(self.class_names) if i != self.free_index]

    def iou(self) -> np.ndarray:
        """(num_labels,) float64 IoU per label id (free included), in [0, 1]; NaN where row+col == 0."""
        cm = self.confusion.astype(np.float64)
        tp = np.diag(cm)
        union = cm.sum(axis=1) + cm.sum(axis=0) - tp
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(union > 0, tp / np.where(union > 0, union, 1.0), np.nan)

    def _index(self, name: str) -> int:
        try:
            return self.class_names.index(name)
        except ValueError:
            raise KeyError(f"unknown class {name!r}; known: {self.class_names}") from None

    def miou(self, subset: Sequence[str] | None = None) -> float:
        """nanmean of the IoUs of `subset` (default: every class but free), in [0, 1]; NaN if all absent."""
        names = self.semantic_names if subset is None else list(subset)
        ious = self.iou()[[self._index(c) for c in names]]
        return float(np.nanmean(ious)) if np.any(np.isfinite(ious)) else math.nan

    def miou_1_16(self) -> float:
        """Occ3D's mIoU without class 0 (`others`): the semantic classes minus the first one."""
        return self.miou(self.semantic_names[1:])

    def miou_star(self, excluded: Sequence[str] = MIOU_STAR_EXCLUDED) -> float:
        """The AGO paper's mIoU*: mIoU without `others` and `other_flat` (names absent here are ignored)."""
        return self.miou([c for c in self.semantic_names if c not in excluded])

    def geometry_iou(self) -> float:
        """IoU of 'occupied' (any non-free label) vs free over the same voxels; NaN if nothing occupied."""
        cm = self.confusion
        f = self.free_index
        occ = np.ones(self.num_labels, dtype=bool)
        occ[f] = False
        tp = cm[np.ix_(occ, occ)].sum()         # GT occupied, predicted occupied (any class)
        fn = cm[occ, f].sum()                   # GT occupied, predicted free
        fp = cm[f, occ].sum()                   # GT free, predicted occupied
        union = tp + fn + fp
        return float(tp / union) if union > 0 else math.nan

    def counts(self) -> dict[str, dict[str, int]]:
        """Per label: GT voxels, predicted voxels, true positives (over the counted voxels)."""
        cm = self.confusion
        return {c: {"gt": int(cm[i].sum()), "pred": int(cm[:, i].sum()), "tp": int(cm[i, i])}
                for i, c in enumerate(self.class_names)}

    def summary(self) -> dict:
        """JSON-able results; IoUs in percent rounded to 2 decimals, None where NaN (absent class)."""
        iou = self.iou()
        table = {} if self.table is None else {"class_table": self.table.name}
        return {
            **table,
            "frames": self.frames,
            "voxels": int(self.confusion.sum()),
            "class_names": self.class_names,
            "free_index": self.free_index,
            "iou": {c: _pct(iou[i]) for i, c in enumerate(self.class_names)},
            "mIoU": _pct(self.miou()),
            "mIoU_1_16": _pct(self.miou_1_16()),
            "mIoU_star": _pct(self.miou_star()),
            "geometry_IoU": _pct(self.geometry_iou()),
            "counts": self.counts(),
            "confusion": self.confusion.tolist(),
        }

    def to_markdown(self, subsets: dict[str, Sequence[str]] | None = None) -> str:
        """A markdown table: one row per label (IoU %, GT voxels, predicted voxels), then the means.

        `subsets` adds rows "mIoU (<name>)" for named class subsets (e.g. known / unknown).
        """
        iou = self.iou()
        cnt = self.counts()
        lines = ["| class | IoU (%) | GT voxels | predicted voxels |", "|---|---:|---:|---:|"]
        for i, c in enumerate(self.class_names):
            v = _pct(iou[i])
            lines.append(f"| {c} | {'n/a' if v is None else f'{v:.2f}'} | {cnt[c]['gt']} | {cnt[c]['pred']} |")
        means = [("**mIoU**", self.miou())]
        if self.semantic_names[:1] == ["others"]:   # Occ3D-nuScenes' variants (not for another table, e.g. Waymo's)
            means += [("mIoU (1..16 / without first class)", self.miou_1_16()),
                      ("mIoU* (without others, other_flat)", self.miou_star())]
        means.append(("geometry IoU", self.geometry_iou()))
        for name, sub in (subsets or {}).items():
            means.append((f"mIoU ({name})", self.miou(sub)))
        for name, val in means:
            v = _pct(val)
            lines.append(f"| {name} | {'n/a' if v is None else f'{v:.2f}'} | | |")
        lines.append("")
        lines.append(f"{self.frames} frame(s), {int(self.confusion.sum())} voxels counted; "
                     "n/a = class absent from GT and predictions (left out of the means).")
        return "\n".join(lines) + "\n"
