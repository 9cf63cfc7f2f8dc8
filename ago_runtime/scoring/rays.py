"""Rays through a voxel grid: the voxels a ray passes, in order, and the first occupied one.

A grid is given by its shape (X, Y, Z), `range_min` (the corner, metres) and `voxel_size` (metres per
voxel per axis): voxel (i, j, k) spans range_min + voxel_size * [i, i + 1) (same for j, k), as
`ago_runtime.geometry.grid.Grid` defines it. Rays start at one `origin` inside the grid and go along
unit `directions` (R, 3).

The walk is Amanatides & Woo's voxel traversal ("A fast voxel traversal algorithm for ray tracing",
1987), run for all rays at once with numpy: at each step every ray still walking is in one voxel,
entered at distance `t_in` and left at `t_out`; it then moves to the neighbour across the nearest
face. A ray stops when it leaves the grid or passes `max_t`. Distances are Euclidean along the ray
(unit directions), from the origin.

- `first_occupied(occupied, ...)`: per ray, the distance at which it enters its first occupied voxel
  (0 when the origin's voxel is occupied; with `at_exit=True` the distance at which it leaves that voxel,
  as SparseOcc's RayIoU measures depth) and that voxel's flat index (C order), or inf / -1 when it
  leaves the grid (or passes `max_t`) without meeting one.
- `passed_voxels(...)`: per ray with a length (e.g. a LiDAR return at that distance), the flat indices
  of the voxels it leaves before reaching that length (`t_out < length`): the space the beam crossed;
  and where each ray enters the voxel its length ends in (the return's depth on the voxel grid).
"""

from __future__ import annotations

import numpy as np


class RayWalk:
    """All rays' walks through the grid, advanced one voxel per `advance()` (rays that are done drop out)."""

    def __init__(self, shape, range_min, voxel_size, origin, directions, max_t=None):
        self.shape = np.asarray(shape, np.int64)
        rmin = np.asarray(range_min, np.float64)
        vs = np.asarray(voxel_size, np.float64)
        o = np.asarray(origin, np.float64).reshape(3)
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        start = np.floor((o - rmin) / vs).astype(np.int64)
        if np.any(start < 0) or np.any(start >= self.shape):
            raise ValueError(f"ray origin {o.tolist()} lies outside the grid")
        n = len(d)
        self.ray = np.arange(n)
        self.idx = np.tile(start, (n, 1))
        self.step = np.where(d > 0, 1, np.where(d < 0, -1, 0)).astype(np.int64)
        with np.errstate(divide="ignore", invalid="ignore"):
            boundary = rmin + (start + (self.step > 0)) * vs          # the face each ray crosses next per axis
            self.t_next = np.where(d != 0, (boundary - o) / d, np.inf)   # distance to it, per axis
            self.t_delta = np.where(d != 0, vs / np.abs(d), np.inf)     # distance between two faces, per axis
        self.t_in = np.zeros(n)
        self.max_t = np.full(n, np.inf) if max_t is None else np.broadcast_to(np.asarray(max_t, np.float64), (n,)).copy()
        self._drop(self.t_in <= self.max_t)

    def __bool__(self) -> bool:
        return len(self.ray) > 0

    @property
    def t_out(self) -> np.ndarray:
        """Where each walking ray leaves its current voxel."""
        return self.t_next.min(axis=1)

    def flat(self) -> np.ndarray:
        """Flat (C order) index of each walking ray's current voxel."""
        return (self.idx[:, 0] * self.shape[1] + self.idx[:, 1]) * self.shape[2] + self.idx[:, 2]

    def _drop(self, keep: np.ndarray) -> None:
        for name in ("ray", "idx", "step", "t_next", "t_delta", "t_in", "max_t"):
            setattr(self, name, getattr(self, name)[keep])

    def advance(self, keep: np.ndarray | None = None) -> None:
        """Drop the rays where `keep` is False, move the others into their next voxel, drop those that left."""
        if keep is not None:
            self._drop(keep)
        axis = self.t_next.argmin(axis=1)
        rows = np.arange(len(axis))
        self.t_in = self.t_next[rows, axis]
        self.idx[rows, axis] += self.step[rows, axis]
        self.t_next[rows, axis] += self.t_delta[rows, axis]
        inside = np.all((self.idx >= 0) & (self.idx < self.shape), axis=1)
        self._drop(inside & (self.t_in <= self.max_t))


def first_occupied(occupied: np.ndarray, range_min, voxel_size, origin, directions,
                   max_t=None, at_exit: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(R,) distance to the first occupied voxel along each ray (where the ray enters it; with `at_exit`, where
    it leaves it; inf: none in the grid / before max_t) and (R,) its flat index (-1: none). `occupied`:
    (X, Y, Z) bool."""
    occ = np.asarray(occupied, bool)
    flat_occ = occ.ravel()
    n = len(np.asarray(directions).reshape(-1, 3))
    depth = np.full(n, np.inf)
    voxel = np.full(n, -1, np.int64)
    walk = RayWalk(occ.shape, range_min, voxel_size, origin, directions, max_t)
    while walk:
        f = walk.flat()
        hit = flat_occ[f]
        depth[walk.ray[hit]] = (walk.t_out if at_exit else walk.t_in)[hit]
        voxel[walk.ray[hit]] = f[hit]
        walk.advance(~hit)
    return depth, voxel


def passed_voxels(shape, range_min, voxel_size, origin, directions, lengths) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique flat indices of the voxels some ray leaves before its length (t_out < length), and (R,)
    the distance at which each ray enters the voxel where its length ends (inf when that is outside the grid)."""
    lengths = np.asarray(lengths, np.float64)
    walk = RayWalk(shape, range_min, voxel_size, origin, directions, lengths)
    seen = np.zeros(int(np.prod(shape)), bool)
    end_entry = np.full(len(lengths), np.inf)
    while walk:
        before = walk.t_out < walk.max_t
        seen[walk.flat()[before]] = True
        end_entry[walk.ray[~before]] = walk.t_in[~before]
        walk.advance(before)     # a ray whose length ends in this voxel is done
    return np.flatnonzero(seen), end_entry


def exit_distance(range_min, range_max, origin, directions) -> np.ndarray:
    """(R,) distance along each ray from `origin` (inside the box) to where it leaves the box range_min..range_max."""
    o = np.asarray(origin, np.float64).reshape(3)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    bound = np.where(d > 0, np.asarray(range_max, np.float64), np.asarray(range_min, np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d != 0, (bound - o) / d, np.inf)
    return t.min(axis=1)
