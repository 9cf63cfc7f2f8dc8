"""Free space by ray casting: which voxels a LiDAR ray passed through before it hit something.

Takes ray origins and end points ((R, 3) metres, both in the keyframe's ego frame, i.e. the
grid's frame) and a `Grid`; gives a flat (X*Y*Z,) bool mask of the voxels each segment
origin -> hit crosses, the hit voxel itself excluded. Voxels behind a hit (occluded) are never
marked. Exact voxel traversal (Amanatides & Woo's 3-D DDA), run for all rays at once in numpy:
one loop iteration advances every still-active ray by one voxel, so the loop runs at most
X + Y + Z times. Segments are clipped to the grid box first; hits outside the grid still clear the
voxels their rays cross inside it.

Grazing rays (`GrazingRule`, `ago pseudo-labels --carve grazing`): a ray that descends to a hit on the
ground far away runs through the ground layer's voxels for metres before its hit voxel, in the air just
above the surface those voxels hold; carving them calls far ground free. Under the rule a descending ray
stops carving where it comes down to `margin` voxel heights above the top of its hit's *foot*: the lowest
voxel of the hit's column (x, y) that holds any hit of the sample's sweeps. A ground hit is its own foot, so
its ray leaves the ground layer (and the lower half of the layer above) uncarved; a hit on a wall or a
vehicle's side has the wall's base or the ground below it as its foot, so its ray still carves the air in
front of it down to just above that, and no ray carves the ground layer in front of a wall's base either.
Level and ascending rays carve as under the default rule (`all`). `grazing_stops` gives the per-ray stop
that `traverse(..., t_stop=...)` honours.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ago_runtime.geometry.grid import Grid


@dataclass(frozen=True)
class GrazingRule:
    """Where a ray descending to its hit stops carving (module docstring)."""

    margin: float = 0.5   # voxel heights above the top face of the foot voxel at which a descending ray stops
    column: bool = True   # the foot is the lowest hit voxel of the hit's column (False: the hit's own voxel)

    def to_dict(self) -> dict:
        return {"margin": float(self.margin), "column": bool(self.column)}


def traverse(origins: np.ndarray, ends: np.ndarray, grid: Grid, t_stop: np.ndarray | None = None) -> np.ndarray:
    """(R, 3) ray origins and hit points (ego, metres) -> (X*Y*Z,) bool: voxels crossed before the hit voxel.

    t_stop (R,): per ray, the fraction of the way origin -> hit from which on it carves nothing (a voxel it
    enters at t >= t_stop is not marked); None: every ray carves up to its hit voxel."""
    shape = np.asarray(grid.shape, dtype=np.int64)
    crossed = np.zeros(int(np.prod(shape)), dtype=bool)
    if len(ends) == 0:
        return crossed
    rmin = np.asarray(grid.range_min, dtype=np.float64)
    vs = np.asarray(grid.voxel_size, dtype=np.float64)
    o = (np.broadcast_to(origins, ends.shape).astype(np.float64) - rmin) / vs   # grid units
    e = (np.asarray(ends, dtype=np.float64) - rmin) / vs
    d = e - o
    end_vox = np.floor(e).astype(np.int64)                                       # may lie outside

    # Clip each segment (t in [0, 1]) to the box [0, shape] (slab method).
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (0.0 - o) / d
        t1 = (shape - o) / d
    moving = d != 0
    inside_axis = (o >= 0) & (o < shape)
    t_lo = np.where(moving, np.minimum(t0, t1), np.where(inside_axis, -np.inf, np.inf))
    t_hi = np.where(moving, np.maximum(t0, t1), np.where(inside_axis, np.inf, -np.inf))
    t_enter = np.maximum(t_lo.max(axis=1), 0.0)
    t_exit = np.minimum(t_hi.min(axis=1), 1.0)
    if t_stop is not None:
        t_exit = np.minimum(t_exit, np.asarray(t_stop, dtype=np.float64))
    keep = t_enter < t_exit
    o, d, end_vox, t_enter, t_exit = o[keep], d[keep], end_vox[keep], t_enter[keep], t_exit[keep]
    if len(o) == 0:
        return crossed

    start = o + t_enter[:, None] * d
    vox = np.clip(np.floor(start).astype(np.int64), 0, shape - 1)
    step = np.sign(d).astype(np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(d != 0, 1.0 / d, np.inf)
        t_delta = np.where(d != 0, np.abs(inv), 0.0)          # never used on an axis that does not move
        t_max = np.where(d != 0, (vox + (step > 0) - o) * inv, np.inf)

    X, Y, Z = (int(v) for v in shape)
    # one array per axis (structure of arrays): cheaper than (R, 3) rows with axis arguments
    vx, vy, vz = (np.ascontiguousarray(vox[:, a]) for a in range(3))
    ex, ey, ez = (np.ascontiguousarray(end_vox[:, a]) for a in range(3))
    sx, sy, sz = (np.ascontiguousarray(step[:, a]) for a in range(3))
    tx, ty, tz = (np.ascontiguousarray(t_max[:, a]) for a in range(3))
    dx, dy, dz = (np.ascontiguousarray(t_delta[:, a]) for a in range(3))
    t_end = t_exit
    for _ in range(X + Y + Z + 3):
        if len(vx) == 0:
            break
        at_hit = (vx == ex) & (vy == ey) & (vz == ez)
        free = ~at_hit
        crossed[((vx[free] * Y + vy[free]) * Z + vz[free])] = True
        # advance every ray along the axis whose voxel boundary comes first
        mx = (tx <= ty) & (tx <= tz)
        my = ~mx & (ty <= tz)
        mz = ~mx & ~my
        t_next = np.where(mx, tx, np.where(my, ty, tz))
        vx += sx * mx
        vy += sy * my
        vz += sz * mz
        tx += dx * mx
        ty += dy * my
        tz += dz * mz
        go = free & (t_next < t_end) & (vx >= 0) & (vx < X) & (vy >= 0) & (vy < Y) & (vz >= 0) & (vz < Z)
        if not go.all():
            vx, vy, vz, ex, ey, ez, sx, sy, sz, tx, ty, tz, dx, dy, dz, t_end = (
                a[go] for a in (vx, vy, vz, ex, ey, ez, sx, sy, sz, tx, ty, tz, dx, dy, dz, t_end))
    return crossed


def unique_rays(origin: np.ndarray, ends: np.ndarray, grid: Grid) -> np.ndarray:
    """One representative end point per distinct end voxel (the first point in it): (R', 3).

    Rays from one origin to points in the same voxel cross nearly the same voxels, so this cuts the
    work by the number of points per voxel at a small cost in coverage.
    """
    if len(ends) == 0:
        return ends
    rmin = np.asarray(grid.range_min)
    vs = np.asarray(grid.voxel_size)
    idx = np.floor((ends - rmin) / vs).astype(np.int64)
    idx -= idx.min(axis=0)
    span = idx.max(axis=0) + 1
    key = (idx[:, 0] * span[1] + idx[:, 1]) * span[2] + idx[:, 2]
    _, first = np.unique(key, return_index=True)
    return ends[np.sort(first)]


_KEY_OFFSET = 1 << 20   # lattice indices within +-2^20 voxels of the grid (far beyond any LiDAR's range)
_Z_BITS = 21


def _lattice_keys(points: np.ndarray, grid: Grid) -> np.ndarray:
    """int64 key of the voxel of the grid's lattice (not clipped to the grid) holding each point (N, 3): x, y, z
    indices in 21 bits each, z lowest, so the keys of one voxel column are contiguous and sorted bottom up."""
    idx = np.floor((np.asarray(points, dtype=np.float64) - np.asarray(grid.range_min)) / np.asarray(grid.voxel_size))
    idx = np.clip(idx, -_KEY_OFFSET + 1, _KEY_OFFSET - 1).astype(np.int64) + _KEY_OFFSET
    return (idx[:, 0] << (2 * _Z_BITS)) | (idx[:, 1] << _Z_BITS) | idx[:, 2]


def occupied_keys(points: np.ndarray, grid: Grid) -> np.ndarray:
    """Sorted distinct lattice keys of the voxels holding points (N, 3), inside the grid or not."""
    return np.unique(_lattice_keys(points, grid))


def grazing_stops(origins: np.ndarray, ends: np.ndarray, grid: Grid, rule: GrazingRule,
                  occupied: np.ndarray) -> np.ndarray:
    """t_stop (R,) for `traverse` under `rule`. A ray that descends to its hit stops carving where it comes down
    to rule.margin voxel heights above the top face of its foot voxel: the lowest voxel of the hit's column that
    holds a hit (`occupied`: occupied_keys over every sweep's points; the hit's own voxel when rule.column is
    False). Every other ray (level, ascending, or never that low) carves up to its hit: t_stop 1."""
    ends = np.asarray(ends, dtype=np.float64)
    o = np.broadcast_to(origins, ends.shape).astype(np.float64)
    vz, z0 = float(grid.voxel_size[2]), float(grid.range_min[2])
    drop = (o[:, 2] - ends[:, 2]) / vz                          # voxel heights; > 0: descending
    stops = np.ones(len(ends), dtype=np.float64)
    down = np.flatnonzero(drop > 0)
    if down.size == 0:
        return stops
    keys = _lattice_keys(ends[down], grid)
    foot = keys
    if rule.column and len(occupied):
        column = keys >> _Z_BITS
        pos = np.minimum(np.searchsorted(occupied, column << _Z_BITS), len(occupied) - 1)
        lowest = occupied[pos]
        foot = np.where((lowest >> _Z_BITS) == column, np.minimum(lowest, keys), keys)
    stop_height = (foot & ((1 << _Z_BITS) - 1)) - _KEY_OFFSET + 1 + rule.margin   # grid units above range_min
    origin_height = (o[down, 2] - z0) / vz
    stops[down] = np.minimum((origin_height - stop_height) / drop[down], 1.0)
    return stops
