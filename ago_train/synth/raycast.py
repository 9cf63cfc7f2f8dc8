"""Analytic primitives and vectorised ray casting against them.

A `PrimitiveSet` holds N primitives in the world frame (metres), struct-of-arrays:
  kind  BOX (yaw-rotated box), CYL (vertical cylinder), ELL (yaw-rotated ellipsoid),
        CONE (vertical cone, apex up);
  center (N,3) the primitive's centre; half (N,3) half extents along its local x, y, z
        (cylinder/cone: half[0] = base radius, half[2] = half height); yaw (N,) about world z;
  cls   (N,) Occ3D class id, or MAP_CLASS = "take the class of the ground-surface raster at the hit";
  material (N,) texture kind (render.py), color (N,3) base albedo 0..1, param (N,) texture parameter;
  obj   (N,) index of the world object it belongs to (-1 = none).
The ground plane z = 0 is implicit (id GROUND in the id buffers); rays that hit nothing get id SKY.

`cast(origin, dirs, prims, rects)` intersects a grid of rays from one origin with the primitives,
each primitive only over its rectangle of rays (culling is done by the sensor: camera projection or
LiDAR azimuth/elevation). It gives the distance along the (unit) ray and the id of the first hit.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

BOX, CYL, ELL, CONE = 0, 1, 2, 3
MAP_CLASS = 254
GROUND, SKY = -1, -2
EPS = 1e-4


@dataclass
class PrimitiveSet:
    kind: np.ndarray
    center: np.ndarray
    half: np.ndarray
    yaw: np.ndarray
    cls: np.ndarray
    material: np.ndarray
    color: np.ndarray
    param: np.ndarray
    obj: np.ndarray

    @classmethod
    def empty(cls) -> "PrimitiveSet":
        return cls(np.zeros(0, np.int8), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.uint8),
                   np.zeros(0, np.uint8), np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32))

    @classmethod
    def from_rows(cls, rows: list[tuple]) -> "PrimitiveSet":
        """rows of (kind, center3, half3, yaw, cls, material, color3, param, obj)."""
        if not rows:
            return cls.empty()
        k, c, h, y, cl, m, co, p, o = zip(*rows)
        return cls(np.array(k, np.int8), np.array(c, np.float64).reshape(-1, 3), np.array(h, np.float64).reshape(-1, 3),
                   np.array(y, np.float64), np.array(cl, np.uint8), np.array(m, np.uint8),
                   np.array(co, np.float32).reshape(-1, 3), np.array(p, np.float32), np.array(o, np.int32))

    def __len__(self) -> int:
        return len(self.kind)

    def subset(self, index) -> "PrimitiveSet":
        return PrimitiveSet(*(getattr(self, f.name)[index] for f in fields(self)))

    @staticmethod
    def concat(sets: list["PrimitiveSet"]) -> "PrimitiveSet":
        sets = [s for s in sets if len(s)]
        if not sets:
            return PrimitiveSet.empty()
        return PrimitiveSet(*(np.concatenate([getattr(s, f.name) for s in sets]) for f in fields(PrimitiveSet)))

    def xy_half_extent(self) -> np.ndarray:
        """(N, 2) half extents of each primitive's world axis-aligned footprint."""
        c, s = np.abs(np.cos(self.yaw)), np.abs(np.sin(self.yaw))
        hx, hy = self.half[:, 0], self.half[:, 1]
        round_ = (self.kind == CYL) | (self.kind == CONE)
        ex = np.where(round_, hx, c * hx + s * hy)
        ey = np.where(round_, hx, s * hx + c * hy)
        return np.stack([ex, ey], axis=1)

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned bounds: (N,3) min, (N,3) max."""
        e = np.concatenate([self.xy_half_extent(), self.half[:, 2:3]], axis=1)
        return self.center - e, self.center + e


def intersect(prims: PrimitiveSet, i: int, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance along the rays `dirs` (m,3) from `origin` (3,) to primitive i; inf where missed.

    Works in the dtype of `dirs` (float32 is enough: distances < 1 km, mm precision)."""
    c, s = float(np.cos(prims.yaw[i])), float(np.sin(prims.yaw[i]))
    rel = np.asarray(origin, np.float64) - prims.center[i]
    ox, oy, oz = c * rel[0] + s * rel[1], -s * rel[0] + c * rel[1], float(rel[2])
    ox, oy = float(ox), float(oy)
    dx = c * dirs[:, 0] + s * dirs[:, 1]
    dy = -s * dirs[:, 0] + c * dirs[:, 1]
    dz = dirs[:, 2]
    hx, hy, hz = (float(v) for v in prims.half[i])
    kind = prims.kind[i]
    inf = np.inf
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if kind == BOX:
            tmin = np.full(len(dz), -inf, dirs.dtype)
            tmax = np.full(len(dz), inf, dirs.dtype)
            for o_, d_, h_ in ((ox, dx, hx), (oy, dy, hy), (oz, dz, hz)):
                inv = 1.0 / d_
                t1 = (-h_ - o_) * inv
                t2 = (h_ - o_) * inv
                np.maximum(tmin, np.minimum(t1, t2), out=tmin)
                np.minimum(tmax, np.maximum(t1, t2), out=tmax)
            return np.where((tmax >= tmin) & (tmin > EPS), tmin, inf)
        if kind == ELL:
            ax, ay, az = ox / hx, oy / hy, oz / hz
            ex, ey, ez = dx / hx, dy / hy, dz / hz
            a = ex * ex + ey * ey + ez * ez
            b = 2.0 * (ex * ax + ey * ay + ez * az)
            cc = ax * ax + ay * ay + az * az - 1.0
            disc = b * b - 4 * a * cc
            t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
            return np.where((disc >= 0) & (t > EPS), t, inf)
        r = hx
        best = np.full(len(dz), inf, dirs.dtype)
        # flat caps: bottom for both, top only for the cylinder
        for zc, allowed in ((-hz, True), (hz, kind == CYL)):
            if not allowed:
                continue
            tc = (zc - oz) / dz
            px = ox + tc * dx
            py = oy + tc * dy
            ok = (tc > EPS) & (px * px + py * py <= r * r)
            best = np.where(ok & (tc < best), tc, best)
        if kind == CYL:
            a = dx * dx + dy * dy
            b = 2 * (ox * dx + oy * dy)
            cc = ox * ox + oy * oy - r * r
        else:  # cone: x^2 + y^2 = k^2 (hz - z)^2, k = r / (2 hz)
            k2 = (r / (2 * hz)) ** 2
            w = hz - oz
            a = dx * dx + dy * dy - k2 * dz * dz
            b = 2 * (ox * dx + oy * dy + k2 * w * dz)
            cc = ox * ox + oy * oy - k2 * w * w
        disc = b * b - 4 * a * cc
        sq = np.sqrt(np.maximum(disc, 0))
        for sign in (-1.0, 1.0):
            t = (-b + sign * sq) / (2 * a)
            z = oz + t * dz
            ok = (disc >= 0) & (t > EPS) & (z >= -hz) & (z <= hz) & np.isfinite(t)
            best = np.where(ok & (t < best), t, best)
        return best


def local_points(prims: PrimitiveSet, ids: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(m,3) world points on primitives `ids` (m,) -> their local coordinates (centre at 0)."""
    rel = points - prims.center[ids]
    c, s = np.cos(prims.yaw[ids]), np.sin(prims.yaw[ids])
    return np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], axis=1)


def surface_normals(prims: PrimitiveSet, ids: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Unit world normals (m,3) at local hit points q (m,3) of primitives ids (m,)."""
    kind = prims.kind[ids]
    n = np.zeros_like(q)
    for k in np.unique(kind):
        sel = np.nonzero(kind == k)[0]
        qs, h = q[sel], prims.half[ids[sel]]
        if k == BOX:
            axis = np.argmax(np.abs(qs) / np.maximum(h, 1e-6), axis=1)
            v = np.zeros_like(qs)
            v[np.arange(len(qs)), axis] = np.sign(qs[np.arange(len(qs)), axis])
        elif k == ELL:
            v = qs / np.maximum(h, 1e-6) ** 2
        elif k == CYL:
            cap = np.abs(qs[:, 2]) > h[:, 2] - 1e-3
            v = np.stack([qs[:, 0], qs[:, 1], np.zeros(len(qs))], 1)
            v[cap] = 0
            v[cap, 2] = np.sign(qs[cap, 2])
        else:
            r, hz = h[:, 0], h[:, 2]
            k2 = (r / (2 * np.maximum(hz, 1e-6))) ** 2
            v = np.stack([qs[:, 0], qs[:, 1], k2 * (hz - qs[:, 2])], 1)
            bottom = qs[:, 2] < -hz + 1e-3
            v[bottom] = (0, 0, -1)
        n[sel] = v
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    c, s = np.cos(prims.yaw[ids]), np.sin(prims.yaw[ids])
    return np.stack([c * n[:, 0] - s * n[:, 1], s * n[:, 0] + c * n[:, 1], n[:, 2]], axis=1)


def cast(origin: np.ndarray, dirs: np.ndarray, prims: PrimitiveSet, rects: list[tuple[int, int, int, int, int]],
         max_distance: float = np.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast a grid of unit rays `dirs` (R, C, 3) from `origin` (3,) against the ground plane and `prims`.

    rects: (primitive index, r0, r1, c0, c1) = test primitive only on dirs[r0:r1, c0:c1].
    Returns t (R, C) distance (dtype of dirs) (inf = nothing), ids (R, C) int32 (primitive index, GROUND or SKY),
    and (N,) int64 per-primitive counts of rays that intersect it at all (visible or occluded).
    """
    origin = np.asarray(origin, np.float64)
    R, C, _ = dirs.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(dirs[..., 2] < -1e-9, -float(origin[2]) / dirs[..., 2], np.inf).astype(dirs.dtype)
    t[t > max_distance] = np.inf
    ids = np.where(np.isfinite(t), GROUND, SKY).astype(np.int32)
    any_hits = np.zeros(len(prims), np.int64)
    for i, r0, r1, c0, c1 in rects:
        sub_d = dirs[r0:r1, c0:c1]
        tn = intersect(prims, i, origin, sub_d.reshape(-1, 3)).reshape(sub_d.shape[:2])
        any_hits[i] += int(np.count_nonzero(np.isfinite(tn)))
        sub_t = t[r0:r1, c0:c1]
        closer = tn < sub_t
        if closer.any():
            sub_t[closer] = tn[closer]
            ids[r0:r1, c0:c1][closer] = i
    return t, ids, any_hits
