"""A spinning multi-beam LiDAR (HDL-32E like, nuScenes LIDAR_TOP mounting) ray-cast against the world.

`scan_lidar(world, prims, config, ego2global, rng) -> LidarScan` casts beams x azimuth steps rays
from the sensor origin (lidar2ego = config.lidar2ego(), LiDAR frame: x = ego right, y = ego
forward, z up). Each ray is tested only against primitives whose azimuth/elevation interval (seen
from the sensor) contains it. Rays without a return within `lidar_max_range` give no point.
Points: (N, 5) float32 [x, y, z, intensity 0..255, ring] in the LiDAR frame; ring 0 = lowest beam.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import SynthConfig
from .raycast import SKY, PrimitiveSet, cast
from .render import albedo_and_class
from .world import World


@dataclass
class LidarScan:
    points: np.ndarray        # (N, 5) float32 LiDAR frame
    points_world: np.ndarray  # (N, 3) float64
    ids: np.ndarray           # (N,) primitive index or GROUND
    classes: np.ndarray       # (N,) Occ3D class of the surface hit
    obj: np.ndarray           # (N,) object index (-1 = scenery / ground)
    origin_world: np.ndarray  # (3,)


def lidar_directions(config: SynthConfig) -> np.ndarray:
    """(beams, steps, 3) unit ray directions in the LiDAR frame; column j has azimuth -pi + 2 pi j / steps."""
    el = config.lidar_elevations()
    az = -np.pi + 2 * np.pi * np.arange(config.lidar_azimuth_steps) / config.lidar_azimuth_steps
    ce = np.cos(el)[:, None]
    shape = (len(el), len(az))
    return np.stack([ce * np.cos(az)[None], ce * np.sin(az)[None], np.broadcast_to(np.sin(el)[:, None], shape)], axis=-1)


def lidar_rects(origin: np.ndarray, lidar_yaw: float, elevations: np.ndarray, steps: int, lo: np.ndarray, hi: np.ndarray,
                max_range: float) -> list[tuple[int, int, int, int, int]]:
    """Ray-grid rectangles (index, ring0, ring1, col0, col1) covering each AABB's angular extent."""
    if len(lo) == 0:
        return []
    B = len(elevations)
    rel_lo, rel_hi = lo - origin, hi - origin
    # horizontal distance range
    dx = np.maximum(np.maximum(rel_lo[:, 0], -rel_hi[:, 0]), 0)
    dy = np.maximum(np.maximum(rel_lo[:, 1], -rel_hi[:, 1]), 0)
    rmin = np.hypot(dx, dy)
    rmax = np.hypot(np.maximum(np.abs(rel_lo[:, 0]), np.abs(rel_hi[:, 0])), np.maximum(np.abs(rel_lo[:, 1]), np.abs(rel_hi[:, 1])))
    inside = rmin < 0.05
    near = rmin < max_range
    zl, zh = rel_lo[:, 2], rel_hi[:, 2]
    el_max = np.where(inside, np.pi / 2, np.arctan2(zh, np.where(zh > 0, np.maximum(rmin, 1e-3), rmax)))
    el_min = np.where(inside, -np.pi / 2, np.arctan2(zl, np.where(zl > 0, rmax, np.maximum(rmin, 1e-3))))
    b0 = np.clip(np.searchsorted(elevations, el_min) - 1, 0, B)
    b1 = np.clip(np.searchsorted(elevations, el_max) + 1, 0, B)
    # azimuth interval around the AABB centre's azimuth
    cxy = (rel_lo[:, :2] + rel_hi[:, :2]) / 2
    psi_c = np.arctan2(cxy[:, 1], cxy[:, 0])
    cx = np.stack([rel_lo[:, 0], rel_hi[:, 0], rel_lo[:, 0], rel_hi[:, 0]], 1)
    cy = np.stack([rel_lo[:, 1], rel_lo[:, 1], rel_hi[:, 1], rel_hi[:, 1]], 1)
    rel = np.angle(np.exp(1j * (np.arctan2(cy, cx) - psi_c[:, None])))
    a_lo = psi_c + rel.min(1) - lidar_yaw
    a_hi = psi_c + rel.max(1) - lidar_yaw
    j_lo = np.floor((a_lo + np.pi) * steps / (2 * np.pi)).astype(np.int64) - 1
    j_hi = np.ceil((a_hi + np.pi) * steps / (2 * np.pi)).astype(np.int64) + 2
    full = inside | (j_hi - j_lo >= steps)
    rects = []
    for i in np.nonzero(near & (b1 > b0))[0]:
        if full[i]:
            rects.append((int(i), int(b0[i]), int(b1[i]), 0, steps))
            continue
        j0 = int(j_lo[i]) % steps
        n = int(j_hi[i] - j_lo[i])
        if j0 + n <= steps:
            rects.append((int(i), int(b0[i]), int(b1[i]), j0, j0 + n))
        else:
            rects.append((int(i), int(b0[i]), int(b1[i]), j0, steps))
            rects.append((int(i), int(b0[i]), int(b1[i]), 0, j0 + n - steps))
    return rects


def scan_lidar(world: World, prims: PrimitiveSet, aabb, config: SynthConfig, ego2global: np.ndarray,
               rng: np.random.Generator, dirs_lidar: np.ndarray | None = None) -> LidarScan:
    if dirs_lidar is None:
        dirs_lidar = lidar_directions(config)
    lidar2world = ego2global @ config.lidar2ego()
    origin = lidar2world[:3, 3]
    R = lidar2world[:3, :3]
    dirs = (dirs_lidar @ R.T).astype(np.float32)
    lidar_yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    rects = lidar_rects(origin, lidar_yaw, config.lidar_elevations(), config.lidar_azimuth_steps, *aabb,
                        config.lidar_max_range)
    t, ids, _ = cast(origin, dirs, prims, rects, max_distance=config.lidar_max_range)
    hit = (ids != SKY) & (t <= config.lidar_max_range)
    ring = np.nonzero(hit)[0]
    tt = t[hit] + rng.normal(0, config.lidar_range_noise, int(hit.sum()))
    d_l = dirs_lidar[hit]
    pts_l = tt[:, None] * d_l
    pts_w = origin + t[hit][:, None] * dirs[hit]
    hid = ids[hit]
    albedo, cls, normal, code = albedo_and_class(world, prims, hid, pts_w)
    cos_inc = np.abs(np.einsum("ij,ij->i", normal, dirs[hit]))
    lum = albedo @ np.array([0.3, 0.5, 0.2])
    intensity = 255 * (0.03 + 0.35 * lum) * (0.3 + 0.7 * cos_inc)
    intensity = np.where(code == 250, 160 + 60 * cos_inc, intensity)  # retro-reflective road paint
    intensity = np.clip(intensity * rng.uniform(0.85, 1.15, len(intensity)), 0, 255)
    points = np.concatenate([pts_l, intensity[:, None], ring[:, None]], axis=1).astype(np.float32)
    obj = np.where(hid >= 0, prims.obj[np.maximum(hid, 0)], -1)
    return LidarScan(points, pts_w, hid, cls, obj, origin)
