"""RayIoU: the occupancy metric of SparseOcc (Liu et al., "Fully Sparse 3D Occupancy Prediction", ECCV 2024),
counted over rays instead of voxels, as SparseOcc's ray_metrics / ego_pose_dataset compute it.

What is counted here:
- origins (`scene_origins`): the LiDAR positions of every keyframe of the frame's scene, past and future,
  the frame's own included, moved into the frame's ego frame (inv(ego2global) @ ego2global_j @
  lidar2ego_j); those with |x| < 39 m and |y| < 39 m are kept, in time order; if more than 8 remain,
  the ones at round(linspace(0, n - 1, 8)). Without poses (`ago metric --gt` without `--data`) one fixed
  origin is used, by default the nuScenes LIDAR_TOP position in the ego frame (0.943, 0, 1.84) m, and
  the numbers are not comparable with published ones. An origin outside the grid (its z beyond the
  grid's height) is skipped and counted (`origins_outside_grid`); SparseOcc would march in from it.
- rays: `lidar_like_rays()`, SparseOcc's query-ray pattern (a LiDAR-like fan: 10 downward pitch angles
  -(pi/2 - atan(k)), k = 1..10, continued upward at the last spacing until 0.21 rad, each at azimuths
  0, 1, ..., 359 degrees; 39 x 360 = 14,040 rays), cast from every origin, not rotated (ego-frame axes).
- along each ray, the ground truth's class and depth are those of its first occupied GT voxel, depth =
  where the ray LEAVES that voxel (`rays.first_occupied(..., at_exit=True)`, as SparseOcc's voxel
  traversal records it); the prediction's likewise (class `free` when it meets nothing in the grid).
- per origin, a ray whose GT meets no occupied voxel in the grid is not counted, nor one whose first GT
  voxel is ignored (255, e.g. a class no prompt covers under `--prompts`). The camera mask is not used.
- for each threshold t in 1, 2, 4 m and class c: TP_c counts the rays with GT class == predicted class == c
  and |depth_pred - depth_gt| < t; GT_c the rays with GT class c; P_c the rays with predicted class c.
  IoU_c(t) = TP_c / (GT_c + P_c - TP_c), counts summed over all rays of all origins of all frames;
  NaN (left out of means) where GT_c + P_c = 0.
- RayIoU@t = mean over the semantic classes of IoU_c(t); RayIoU = mean of RayIoU@1, @2, @4.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ago_runtime.scoring.rays import first_occupied

THRESHOLDS = (1.0, 2.0, 4.0)
NUSCENES_LIDAR_ORIGIN = (0.943, 0.0, 1.84)   # LIDAR_TOP in the ego frame (calibrated_sensor, metres)
ORIGIN_XY_LIMIT = 39.0    # metres: scene origins farther along x or y are dropped
MAX_ORIGINS = 8


def scene_origins(ref_ego2global: np.ndarray, scene_poses) -> np.ndarray:
    """(T, 3) ray origins of one frame: `scene_poses` lists (lidar2ego, ego2global) of every keyframe of its scene
    in time order (the frame's own included); see the module doc."""
    inv = np.linalg.inv(np.asarray(ref_ego2global, np.float64))
    out = [(inv @ np.asarray(e2g, np.float64) @ np.asarray(l2e, np.float64))[:3, 3] for l2e, e2g in scene_poses]
    out = [o for o in out if abs(o[0]) < ORIGIN_XY_LIMIT and abs(o[1]) < ORIGIN_XY_LIMIT]
    if len(out) > MAX_ORIGINS:
        out = [out[i] for i in np.round(np.linspace(0, len(out) - 1, MAX_ORIGINS)).astype(np.int64)]
    return np.asarray(out, np.float64).reshape(-1, 3)


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
    """(R,) class of the first non-free voxel along each ray (free_index when none) and (R,) where the ray
    leaves it (inf)."""
    occupied = np.asarray(sem) != free_index
    depth, voxel = first_occupied(occupied, range_min, voxel_size, origin, directions, at_exit=True)
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
        self.origins_used = 0
        self.origins_outside_grid = 0
        self.scene_origins = False    # True once a frame was given its scene's origins

    def update(self, pred: np.ndarray, gt: np.ndarray, range_min, voxel_size, origins=None) -> None:
        """Add one frame: pred and gt (X, Y, Z) label volumes on the same grid; `origins` (T, 3) in its ego frame
        (`scene_origins`), default the fixed `origin`."""
        if origins is not None:
            self.scene_origins = True
        rmin = np.asarray(range_min, np.float64)
        rmax = rmin + np.asarray(voxel_size, np.float64) * np.asarray(np.shape(gt))
        for o in np.asarray([self.origin] if origins is None else origins, np.float64).reshape(-1, 3):
            if np.any(o < rmin) or np.any(o >= rmax):
                self.origins_outside_grid += 1
                continue
            self._add_origin(pred, gt, rmin, voxel_size, o)
            self.origins_used += 1
        self.frames += 1

    def _add_origin(self, pred, gt, range_min, voxel_size, origin) -> None:
        n = len(self.class_names)
        g_lab, g_dep = ray_class_depth(gt, self.free_index, range_min, voxel_size, origin, self.directions)
        p_lab, p_dep = ray_class_depth(pred, self.free_index, range_min, voxel_size, origin, self.directions)
        keep = (g_lab != self.free_index) & (g_lab < n)    # GT met something, and not an ignored (255) voxel
        g_lab, g_dep, p_lab, p_dep = g_lab[keep], g_dep[keep], p_lab[keep], p_dep[keep]
        self.gt += np.bincount(g_lab, minlength=n)[:n]
        self.pred += np.bincount(p_lab[p_lab < n], minlength=n)[:n]
        same = g_lab == p_lab
        for i, t in enumerate(self.thresholds):
            ok = same & (np.abs(p_dep - g_dep) < t)
            self.tp[i] += np.bincount(g_lab[ok], minlength=n)[:n]
        self.rays += int(keep.sum())

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
            "frames": self.frames, "rays_counted": self.rays,
            "origins": "scene (SparseOcc)" if self.scene_origins else "fixed",
            "origin_m": None if self.scene_origins else list(self.origin),
            "origins_used": self.origins_used, "origins_outside_grid": self.origins_outside_grid,
            "rays_per_frame": int(len(self.directions)), "thresholds_m": list(self.thresholds),
            "RayIoU": pct(self.ray_iou()),
            **{f"RayIoU@{t:g}": pct(v) for t, v in zip(self.thresholds, self.ray_iou_at())},
            "per_class": {self.class_names[c]: {f"@{t:g}": pct(iou[i, c]) for i, t in enumerate(self.thresholds)}
                          for c in self.semantic},
        }
