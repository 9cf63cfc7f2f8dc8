"""RayIoU: the occupancy metric of SparseOcc (Liu et al., "Fully Sparse 3D Occupancy Prediction", ECCV 2024),
counted over rays instead of voxels.

What is counted here:
- rays: `lidar_like_rays()`, SparseOcc's query-ray pattern (a LiDAR-like fan: 10 downward pitch angles
  -(pi/2 - atan(k)), k = 1..10, continued upward at the last spacing until 0.21 rad, each at azimuths
  0, 1, ..., 359 degrees; 39 x 360 = 14,040 rays), cast from one origin, by default the nuScenes LIDAR_TOP
  position in the ego frame (0.943, 0, 1.84) m. SparseOcc casts them from the LiDAR origins of several
  nearby frames; here it is the keyframe's own origin only (`--ray-origin` changes it).
- along each ray, the ground truth's class and depth are those of its first occupied GT voxel
  (`rays.first_occupied`: depth = where the ray enters that voxel); the prediction's are those of its
  first predicted-occupied voxel (class `free` and no depth when it meets none in the grid).
- a ray whose GT meets no occupied voxel in the grid is not counted, nor one whose first GT voxel is
  ignored (255, e.g. a class no prompt covers under `--prompts`). The camera mask is not used.
- for each threshold t in 1, 2, 4 m and class c: TP_c counts the rays with GT class == predicted class == c
  and |depth_pred - depth_gt| < t; GT_c the rays with GT class c; P_c the rays with predicted class c.
  IoU_c(t) = TP_c / (GT_c + P_c - TP_c) summed over all frames (like the Occ3D metric, not per frame);
  NaN (left out of means) where GT_c + P_c = 0.
- RayIoU@t = mean over classes of IoU_c(t); RayIoU = mean of RayIoU@1, @2, @4.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ago_runtime.scoring.rays import first_occupied

THRESHOLDS = (1.0, 2.0, 4.0)
NUSCENES_LIDAR_ORIGIN = (0.943, 0.0, 1.84)   # LIDAR_TOP in the ego frame (calibrated_sensor, metres)


def lidar_like_rays() -> np.ndarray:
    """(R, 3) unit directions of SparseOcc's query rays (x forward, y left, z up), see the module doc."""
    pitch = [-(math.pi / 2 - math.atan(k + 1)) for k in range(10)]
    while pitch[-1] < 0.21:     # nuScenes LiDAR field of view: -0.54 .. 0.21 rad
        pitch.append(pitch[-1] + (pitch[-1] - pitch[-2]))
    p = np.asarray(pitch)[:, None]
    a = np.deg2rad(np.arange(0, 360, 1.0))[None, :]
    rays = np.stack([np.cos(p) * np.cos(a), np.cos(p) * np.sin(a), np.sin(p) * np.ones_like(a)], axis=-1)
    return rays.reshape(-1, 3)


def ray_class_depth(sem: np.ndarray, free_index: int, range_min, voxel_size, origin, directions):
    """(R,) class of the first non-free voxel along each ray (free_index when none) and (R,) its depth (inf)."""
    occupied = np.asarray(sem) != free_index
    depth, voxel = first_occupied(occupied, range_min, voxel_size, origin, directions)
    labels = np.full(len(depth), free_index, np.int64)
    hit = voxel >= 0
    labels[hit] = np.asarray(sem).ravel()[voxel[hit]]
    return labels, depth


class RayIoU:
    """TP / GT / predicted ray counts per threshold and class, summed over frames."""

    def __init__(self, class_names: Sequence[str], free_index: int, thresholds: Sequence[float] = THRESHOLDS,
                 origin=NUSCENES_LIDAR_ORIGIN, directions: np.ndarray | None = None):
        self.class_names = list(class_names)
        self.free_index = int(free_index)
        self.thresholds = tuple(float(t) for t in thresholds)
        self.origin = tuple(float(v) for v in origin)
        self.directions = lidar_like_rays() if directions is None else np.asarray(directions, np.float64)
        n = len(self.class_names)
        self.tp = np.zeros((len(self.thresholds), n), np.int64)
        self.gt = np.zeros(n, np.int64)
        self.pred = np.zeros(n, np.int64)
        self.rays = 0
        self.frames = 0

    def update(self, pred: np.ndarray, gt: np.ndarray, range_min, voxel_size) -> None:
        """Add one frame: pred and gt (X, Y, Z) label volumes on the same grid."""
        n = len(self.class_names)
        g_lab, g_dep = ray_class_depth(gt, self.free_index, range_min, voxel_size, self.origin, self.directions)
        p_lab, p_dep = ray_class_depth(pred, self.free_index, range_min, voxel_size, self.origin, self.directions)
        keep = (g_lab != self.free_index) & (g_lab < n)    # GT met something, and not an ignored (255) voxel
        g_lab, g_dep, p_lab, p_dep = g_lab[keep], g_dep[keep], p_lab[keep], p_dep[keep]
        self.gt += np.bincount(g_lab, minlength=n)[:n]
        self.pred += np.bincount(p_lab[p_lab < n], minlength=n)[:n]
        same = g_lab == p_lab
        for i, t in enumerate(self.thresholds):
            ok = same & (np.abs(p_dep - g_dep) < t)
            self.tp[i] += np.bincount(g_lab[ok], minlength=n)[:n]
        self.rays += int(keep.sum())
        self.frames += 1

    @property
    def semantic(self) -> list[int]:
        return [i for i in range(len(self.class_names)) if i != self.free_index]

    def iou(self) -> np.ndarray:
        """(T, C) IoU per threshold and class (free included, NaN where GT_c + P_c = 0)."""
        union = self.gt[None, :] + self.pred[None, :] - self.tp
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(union > 0, self.tp / np.where(union > 0, union, 1), np.nan)

    def ray_iou_at(self) -> np.ndarray:
        """(T,) mean over the semantic classes of IoU_c(t) (NaN classes left out)."""
        iou = self.iou()[:, self.semantic]
        return np.array([np.nanmean(r) if np.any(np.isfinite(r)) else np.nan for r in iou])

    def ray_iou(self) -> float:
        at = self.ray_iou_at()
        return float(np.mean(at)) if np.all(np.isfinite(at)) else math.nan

    def summary(self) -> dict:
        def pct(x):
            return None if not np.isfinite(x) else round(float(x) * 100, 2)

        iou = self.iou()
        return {
            "frames": self.frames, "rays_counted": self.rays, "origin_m": list(self.origin),
            "rays_per_frame": int(len(self.directions)), "thresholds_m": list(self.thresholds),
            "RayIoU": pct(self.ray_iou()),
            **{f"RayIoU@{t:g}": pct(v) for t, v in zip(self.thresholds, self.ray_iou_at())},
            "per_class": {self.class_names[c]: {f"@{t:g}": pct(iou[i, c]) for i, t in enumerate(self.thresholds)}
                          for c in self.semantic},
        }
