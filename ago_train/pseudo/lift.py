"""Lifting 2-D image results onto 3-D points: projection, label lookup, feature sampling.

Takes points in an ego frame ((N, 3) metres, x forward, y left, z up) and the `Rig` whose
`cam2ego` refers to that same ego frame; gives, per point, the camera that sees it and the pixel
position (u, v) in that camera's native image (continuous coordinates: pixel (i, j) covers
u in [i, i+1), v in [j, j+1)).

Camera choice: a point inside several images (the overlaps between neighbouring cameras) is
given to the camera in which it lies **nearest the image centre** (smallest normalised distance
((u - W/2)/W)^2 + ((v - H/2)/H)^2), i.e. where lenses distort least; ties go to the earlier camera
in CAMERA_NAMES order. A point only takes what that one camera says: if that camera has no label
there, the point has no label (it is not looked up again in the other camera).
"""

from __future__ import annotations

import numpy as np

from ago_runtime.geometry.camera import Rig

NO_CAMERA = -1
NO_LABEL = 255


def assign_cameras(points_ego: np.ndarray, rig: Rig) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) ego points -> camera index (N,) int64 (index into rig order, -1 = in no image) and uv (N, 2) float64."""
    n = len(points_ego)
    cam_idx = np.full(n, NO_CAMERA, dtype=np.int64)
    uv_best = np.zeros((n, 2), dtype=np.float64)
    best = np.full(n, np.inf)
    for ci, cam in enumerate(rig):
        uv, _depth, ok = cam.project(points_ego)
        score = ((uv[:, 0] - cam.width / 2) / cam.width) ** 2 + ((uv[:, 1] - cam.height / 2) / cam.height) ** 2
        better = ok & (score < best)
        cam_idx[better] = ci
        uv_best[better] = uv[better]
        best[better] = score[better]
    return cam_idx, uv_best


def pixel_lookup(label_map: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Value of an (H, W) map at the pixels containing continuous positions uv (n, 2) -> (n,)."""
    h, w = label_map.shape[:2]
    u = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, w - 1)
    v = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, h - 1)
    return label_map[v, u]


def sample_bilinear(feature_map: np.ndarray, uv: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """Bilinearly sample a (C, h, w) map at image positions uv (n, 2) of an image of size (W, H) -> (n, C) float32.

    The map may have any stride: map cell (j, i) covers image pixels [i*W/w, (i+1)*W/w) x [j*H/h, (j+1)*H/h),
    and its value sits at the cell centre. Positions beyond the outermost centres take the edge value.
    """
    c, h, w = feature_map.shape
    cells, weights = _bilinear_taps(uv, (h, w), image_size)
    rows = np.ascontiguousarray(np.moveaxis(feature_map, 0, -1)).reshape(h * w, c)   # (h*w, C): row gathers
    out = rows[cells[0]].astype(np.float32) * weights[0, :, None].astype(np.float32)
    for k in range(1, 4):
        out += rows[cells[k]].astype(np.float32) * weights[k, :, None].astype(np.float32)
    return out


def _bilinear_taps(uv: np.ndarray, map_hw: tuple[int, int], image_size: tuple[int, int]):
    """Flat cell indices (4, n) and weights (4, n) of the bilinear taps of positions uv on an (h, w) map."""
    h, w = map_hw
    width, height = image_size
    x = np.clip(uv[:, 0] * (w / width) - 0.5, 0.0, w - 1)
    y = np.clip(uv[:, 1] * (h / height) - 0.5, 0.0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    cells = np.stack([y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1])
    weights = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    return cells, weights


def feature_sums_per_voxel(flat_voxel: np.ndarray, uv: np.ndarray, feature_map_hwc: np.ndarray,
                           image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sum of the bilinearly sampled features of the points in each voxel, without a per-point feature array.

    flat_voxel (n,) voxel of each point, uv (n, 2) its image position, feature_map_hwc (h, w, C).
    Gives (voxels (U,) int64 sorted, sums (U, C) float32, point counts (U,) int64). Equal to
    summing sample_bilinear(...) per voxel, but the weights of points that share a voxel and a
    map cell are added first, so the work on C-vectors is per (voxel, cell) pair, not per point.
    """
    h, w, c = feature_map_hwc.shape
    flat_voxel = np.asarray(flat_voxel, dtype=np.int64)
    if flat_voxel.size == 0:
        return np.zeros(0, np.int64), np.zeros((0, c), np.float32), np.zeros(0, np.int64)
    cells, weights = _bilinear_taps(uv, (h, w), image_size)
    keys = (flat_voxel[None, :] * (h * w) + cells).ravel()
    pair, inverse = np.unique(keys, return_inverse=True)
    pair_w = np.bincount(inverse, weights=weights.ravel(), minlength=len(pair)).astype(np.float32)
    pair_voxel, pair_cell = pair // (h * w), pair % (h * w)
    table = np.asarray(feature_map_hwc, dtype=np.float32).reshape(h * w, c)   # convert the small map once
    starts = np.flatnonzero(np.r_[True, pair_voxel[1:] != pair_voxel[:-1]])
    voxels = pair_voxel[starts]
    rank = np.cumsum(np.r_[True, pair_voxel[1:] != pair_voxel[:-1]]) - 1      # voxel rank of each pair
    sums = np.zeros((len(voxels), c), dtype=np.float32)
    chunk = max(256, (1 << 20) // (4 * c))          # ~1 MB of weighted features at a time (stays in cache)
    for a in range(0, len(pair), chunk):
        r = rank[a:a + chunk]
        local = np.flatnonzero(np.r_[True, r[1:] != r[:-1]])
        part = np.add.reduceat(table[pair_cell[a:a + chunk]] * pair_w[a:a + chunk, None], local, axis=0)
        sums[r[local]] += part                      # ranks within a chunk are distinct
    counts = np.bincount(np.searchsorted(voxels, flat_voxel), minlength=len(voxels))
    return voxels, sums, counts


def lift_labels(cam_idx: np.ndarray, uv: np.ndarray, label_maps: list[np.ndarray | None]) -> np.ndarray:
    """Per-point labels (N,) uint8 from per-camera (H, W) uint8 label maps (rig order; 255 = no label).

    Points in no image, or whose camera's map is None, get 255.
    """
    labels = np.full(len(cam_idx), NO_LABEL, dtype=np.uint8)
    for ci, lmap in enumerate(label_maps):
        if lmap is None:
            continue
        sel = np.flatnonzero(cam_idx == ci)
        if sel.size:
            labels[sel] = pixel_lookup(lmap, uv[sel])
    return labels


def lift_features(cam_idx: np.ndarray, uv: np.ndarray, feature_maps: list[np.ndarray], rig: Rig
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per-point features for the points in some image.

    Gives (rows (M,) int64 indices of the points that have a feature, feats (M, C) float32).
    """
    rows_all, feats_all = [], []
    for ci, (cam, fmap) in enumerate(zip(rig, feature_maps)):
        sel = np.flatnonzero(cam_idx == ci)
        if sel.size == 0:
            continue
        rows_all.append(sel)
        feats_all.append(sample_bilinear(fmap, uv[sel], (cam.width, cam.height)))
    if not rows_all:
        c = feature_maps[0].shape[0] if feature_maps else 0
        return np.zeros(0, dtype=np.int64), np.zeros((0, c), dtype=np.float32)
    rows = np.concatenate(rows_all)
    order = np.argsort(rows, kind="stable")
    return rows[order], np.concatenate(feats_all)[order]
