"""Occ3D-format ground truth of one keyframe, in the keyframe's ego frame on a `Grid`.

semantics (any-occupied rule with painting priority): each voxel is cut into S x S x S sub-samples
(S = config.gt_samples_per_axis, default 2); a primitive labels every voxel in which at least one
sub-sample lies inside it. Primitives are painted in order: ground surface first (one voxel layer,
the voxel holding z = -1 mm at the column centre, class from the world's surface raster: road,
sidewalk, terrain, other_flat ...), then static scenery (buildings, walls, poles, trees ...), then
movable objects, so a later primitive overwrites an earlier one in a shared voxel; within each group
the order follows PAINT_PRIORITY (manmade, vegetation, others ... bicycle, pedestrian, traffic cone
last), so thin and rare classes survive on coarse grids. Primitives thinner
than one sub-sample spacing are inflated by half a spacing so poles/wheels are not lost between
samples. Everything else is free (17); voxels below the ground layer are free too (unobserved).
Boxes and cylinders are vertical extrusions, so their test is 2-D footprint x z interval.

mask_lidar: voxels a LiDAR ray passes through between the sensor and its return (sampled every half
voxel) plus the voxel of the return (Occ3D-style ray casting, one sweep). Rays without a return
observe nothing.
mask_camera: a voxel is visible if its centre or the centre of its top face projects into some
camera with a z-depth <= the rendered depth at that pixel + half the voxel diagonal (sky pixels: any
depth). The top-face probe keeps ground voxels seen at grazing angles (the raised sidewalk surface
lies above the centre of its voxel) visible.
"""

from __future__ import annotations

import numpy as np

from ago_runtime.geometry.camera import Rig
from ago_runtime.classes import FREE, OCC3D_WAYMO
from ago_runtime.geometry.grid import Grid
from ago_runtime.formats.occ3d import Occ3DLabels
from ago_runtime.formats.occ3d_waymo import Occ3DWaymoLabels

from .raycast import BOX, CONE, CYL, ELL, MAP_CLASS, PrimitiveSet
from .waymo_labels import NUSCENES_TO_WAYMO, fov_mask, waymo_label_of
from .builder import SURFACE_CLASS
from .world import World


# Painting order within scenery and within movable objects (later wins a shared voxel): big and
# common classes first, thin and rare ones last so that coarse grids keep them.
PAINT_PRIORITY = np.zeros(256, np.int64)
for _rank, _cls in enumerate((15, 16, 0, 12, 13, 14, 11, 9, 3, 10, 5, 4, 1, 6, 2, 7, 8)):
    PAINT_PRIORITY[_cls] = _rank


def _axis_samples(lo: float, size: float, i0: int, i1: int, S: int) -> np.ndarray:
    """Sub-sample coordinates of voxels i0..i1-1 along one axis, (i1-i0)*S values, voxel-major."""
    i = np.arange(i0, i1)[:, None]
    s = (np.arange(S)[None, :] + 0.5) / S
    return (lo + (i + s) * size).ravel()


def semantics(world: World, prims: PrimitiveSet, ego2global: np.ndarray, grid: Grid, S: int = 2,
              labels_of: np.ndarray | None = None, surface_lut: np.ndarray | None = None,
              free: int = FREE) -> np.ndarray:
    """(X, Y, Z) uint8 labels (module docstring). By default Occ3D-nuScenes ids; another class table
    gives `labels_of` (one label per primitive of `prims`), `surface_lut` (256: Occ3D-nuScenes ground
    class -> label) and its `free` id. The painting order stays the one of the Occ3D-nuScenes classes."""
    X, Y, Z = grid.shape
    lo_g = np.asarray(grid.range_min, float)
    vs = np.asarray(grid.voxel_size, float)
    labels = np.full((X, Y, Z), free, np.uint8)
    R = ego2global[:3, :3]
    t = ego2global[:3, 3]
    # ground layer
    k_ground = int(np.floor((-1e-3 - t[2] * 0 - lo_g[2]) / vs[2]))
    xs, ys, _ = grid.axis_centres()
    cx, cy = np.meshgrid(xs, ys, indexing="ij")
    wx = R[0, 0] * cx + R[0, 1] * cy + t[0]
    wy = R[1, 0] * cx + R[1, 1] * cy + t[1]
    if 0 <= k_ground < Z:
        ground = SURFACE_CLASS[world.surface_at(np.stack([wx, wy], -1))]
        labels[:, :, k_ground] = ground if surface_lut is None else surface_lut[ground]
    # primitives, static first then movable objects
    yaw_e = np.arctan2(R[1, 0], R[0, 0])
    rel = prims.center - t
    c_e = rel @ R  # world -> ego: R^T (p - t)
    yaw_l = prims.yaw - yaw_e
    tmp = PrimitiveSet(prims.kind, c_e, prims.half, yaw_l, prims.cls, prims.material, prims.color, prims.param, prims.obj)
    lo, hi = tmp.aabb()
    hi_g = lo_g + vs * np.array([X, Y, Z])
    inside = np.all(hi > lo_g, axis=1) & np.all(lo < hi_g, axis=1) & (prims.cls != MAP_CLASS)
    order = np.nonzero(inside)[0]
    rank = (prims.obj[order] >= 0) * 100 + PAINT_PRIORITY[prims.cls[order]]
    order = order[np.argsort(rank, kind="stable")]
    spacing = vs / S
    for p in order:
        i0, j0, k0 = np.clip(np.floor((lo[p] - lo_g) / vs).astype(int), 0, [X, Y, Z])
        i1, j1, k1 = np.clip(np.floor((hi[p] - lo_g) / vs).astype(int) + 1, 0, [X, Y, Z])
        if i1 <= i0 or j1 <= j0 or k1 <= k0:
            continue
        h = prims.half[p].copy()
        kind = prims.kind[p]
        pad = np.where(h < spacing, spacing / 2, 0.0)
        if kind in (CYL, CONE):
            pad[1] = pad[0]
        sx = _axis_samples(lo_g[0], vs[0], i0, i1, S) - c_e[p, 0]
        sy = _axis_samples(lo_g[1], vs[1], j0, j1, S) - c_e[p, 1]
        sz = _axis_samples(lo_g[2], vs[2], k0, k1, S) - c_e[p, 2]
        c, s = np.cos(yaw_l[p]), np.sin(yaw_l[p])
        lx = c * sx[:, None] + s * sy[None, :]
        ly = -s * sx[:, None] + c * sy[None, :]
        ni, nj, nk = i1 - i0, j1 - j0, k1 - k0
        if kind in (BOX, CYL):
            if kind == BOX:
                foot = (np.abs(lx) <= h[0] + pad[0]) & (np.abs(ly) <= h[1] + pad[1])
            else:
                foot = lx * lx + ly * ly <= (h[0] + pad[0]) ** 2
            col = foot.reshape(ni, S, nj, S).any(axis=(1, 3))
            zk = (np.abs(sz) <= h[2] + pad[2]).reshape(nk, S).any(axis=1)
            occ = col[:, :, None] & zk[None, None, :]
        elif kind == ELL:
            a = h + pad
            v = (lx / a[0]) ** 2 + (ly / a[1]) ** 2
            occ3 = v[:, :, None] + (sz / a[2])[None, None, :] ** 2 <= 1.0
            occ = occ3.reshape(ni, S, nj, S, nk, S).any(axis=(1, 3, 5))
        else:  # cone, apex up
            rr = (h[0] + pad[0]) * (h[2] - sz) / (2 * h[2])
            occ3 = ((lx * lx + ly * ly)[:, :, None] <= (rr ** 2)[None, None, :]) & (np.abs(sz) <= h[2] + pad[2])[None, None, :]
            occ = occ3.reshape(ni, S, nj, S, nk, S).any(axis=(1, 3, 5))
        labels[i0:i1, j0:j1, k0:k1][occ] = prims.cls[p] if labels_of is None else labels_of[p]
    return labels


def lidar_mask(grid: Grid, origin_ego: np.ndarray, points_ego: np.ndarray, chunk: int = 8000) -> np.ndarray:
    """(X,Y,Z) uint8: voxels traversed by the rays origin -> point, plus the points' voxels."""
    X, Y, Z = grid.shape
    mask = np.zeros(X * Y * Z, np.uint8)
    lo = np.asarray(grid.range_min, float)
    hi = np.asarray(grid.range_max, float)
    step = float(min(grid.voxel_size)) / 2
    o = np.asarray(origin_ego, float)
    for a in range(0, len(points_ego), chunk):
        p = np.asarray(points_ego[a:a + chunk, :3], float)
        d = p - o
        rng_ = np.linalg.norm(d, axis=1)
        d = d / np.maximum(rng_[:, None], 1e-9)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo - o) / d
            t2 = (hi - o) / d
        t_in = np.maximum(np.nanmax(np.minimum(t1, t2), axis=1), 0)
        t_out = np.minimum(np.nanmin(np.maximum(t1, t2), axis=1), rng_)
        n = np.where(t_out > t_in, np.ceil((t_out - t_in) / step), 0).astype(np.int64)
        total = int(n.sum())
        if total:
            ray = np.repeat(np.arange(len(p)), n)
            k = np.arange(total) - np.repeat(np.cumsum(n) - n, n)
            tt = t_in[ray] + step * (k + 0.5)
            tt = np.minimum(tt, t_out[ray])
            samples = o + tt[:, None] * d[ray]
            idx, ok = grid.points_to_index(samples)
            mask[grid.flat_index(idx[ok])] = 1
        idx, ok = grid.points_to_index(p)
        mask[grid.flat_index(idx[ok])] = 1
    return mask.reshape(X, Y, Z)


def camera_mask(grid: Grid, rig: Rig, depths: dict[str, np.ndarray]) -> np.ndarray:
    """(X,Y,Z) uint8: voxels whose centre is seen by at least one camera (see module doc)."""
    xs, ys, zs = (a.astype(np.float32) for a in grid.axis_centres())
    tol = np.float32(0.5 * float(np.linalg.norm(grid.voxel_size)))
    mask = np.zeros(grid.shape, bool)
    top = np.float32(0.49 * grid.voxel_size[2])
    for cam in rig:
        m = cam.ego2img.astype(np.float32)  # ego -> (u d, v d, d): separable in x, y, z
        for dz in (np.float32(0.0), top):   # probe the voxel centre and its top-face centre
            def comp(r):
                return ((m[r, 0] * xs)[:, None, None] + (m[r, 1] * ys)[None, :, None]
                        + (m[r, 2] * (zs + dz) + m[r, 3])[None, None, :])
            d = comp(2)
            inv = 1.0 / np.maximum(d, np.float32(0.1))
            u = comp(0) * inv
            v = comp(1) * inv
            ok = (d > 0.1) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
            ui = np.where(ok, u, 0).astype(np.int32)
            vi = np.where(ok, v, 0).astype(np.int32)
            r = depths[cam.name][vi, ui]
            mask |= ok & ((r == 0) | (d <= r + tol))
    return mask.astype(np.uint8)


def occupancy_gt(world: World, prims: PrimitiveSet, ego2global: np.ndarray, grid: Grid, rig: Rig,
                 depths: dict[str, np.ndarray], lidar_origin_world: np.ndarray, lidar_points_world: np.ndarray,
                 samples_per_axis: int = 2) -> Occ3DLabels:
    """The Occ3D labels of one keyframe (see the module docstring for the rules)."""
    sem = semantics(world, prims, ego2global, grid, samples_per_axis)
    world2ego = np.linalg.inv(ego2global)
    o = world2ego[:3, :3] @ lidar_origin_world + world2ego[:3, 3]
    pe = lidar_points_world @ world2ego[:3, :3].T + world2ego[:3, 3]
    return Occ3DLabels(sem, lidar_mask(grid, o, pe), camera_mask(grid, rig, depths))


def occupancy_gt_waymo(world: World, prims: PrimitiveSet, ego2global: np.ndarray, grid: Grid, cameras,
                       depths: dict[str, np.ndarray], lidar_origin_world: np.ndarray, lidar_points_world: np.ndarray,
                       samples_per_axis: int = 2) -> Occ3DWaymoLabels:
    """The Occ3D-Waymo labels of one keyframe: the same rules as `occupancy_gt`, labels in OCC3D_WAYMO
    (`waymo_labels.waymo_label_of`, free = 23), plus `infov` (`waymo_labels.fov_mask`)."""
    sem = semantics(world, prims, ego2global, grid, samples_per_axis,
                    labels_of=waymo_label_of(prims.cls, prims.material), surface_lut=NUSCENES_TO_WAYMO,
                    free=OCC3D_WAYMO.free_id)
    world2ego = np.linalg.inv(ego2global)
    o = world2ego[:3, :3] @ lidar_origin_world + world2ego[:3, 3]
    pe = lidar_points_world @ world2ego[:3, :3].T + world2ego[:3, 3]
    return Occ3DWaymoLabels(sem, lidar_mask(grid, o, pe), camera_mask(grid, cameras, depths), fov_mask(grid, cameras))
