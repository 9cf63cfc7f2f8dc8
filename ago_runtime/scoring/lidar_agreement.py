"""How well a predicted occupancy agrees with a keyframe's real LiDAR: three measures that need no Occ3D labels.

Inputs per frame: the prediction's occupied voxels (X, Y, Z) bool on a grid (`range_min`, `voxel_size`),
the keyframe's LiDAR returns in the same ego frame ((N, 3) metres) and the LiDAR origin there (the
sensor's position: lidar2ego's translation). Which returns count: those inside the grid and at least
`MIN_RANGE` (1 m) from the sensor (the nuScenes devkit's `remove_close` radius: returns off the ego car's
own roof). Each counted return is one ray, origin -> return, of measured depth = their distance.

(a) depth error: along each ray, the predicted depth is where the ray enters its first predicted-occupied
    voxel (`rays.first_occupied`); a ray that meets none before leaving the grid gets the distance at
    which it leaves the grid (the prediction says "free all the way"). The measured depth is taken on the
    same voxel grid: where the ray enters the voxel that holds its return (`rays.passed_voxels`), so that
    a prediction whose first occupied voxel along the ray is the return's own voxel scores exactly 0.
    Error = |predicted - measured| in metres; reported: mean, median, share under 1 m, and the share of
    rays that met no occupied voxel. A voxel map that is right about every return still reads short on
    rays that graze an occupied layer before their own voxel (low beams over the ground layer).
(b) hit share: the share of counted returns whose voxel is predicted occupied.
(c) seen-free share: of the predicted-occupied voxels, the share that some ray crossed entirely before its
    return (`rays.passed_voxels`: left the voxel at a distance < the measured depth) and that hold no
    return of this sweep: space the LiDAR saw through, so free. Voxels no ray crossed are not judged.

Frames are pooled for the overall numbers (every ray and every predicted-occupied voxel of every frame
counts once), so a frame with more returns weighs more. Only the keyframe's own sweep is used.
"""

from __future__ import annotations

import numpy as np

from ago_runtime.scoring.rays import exit_distance, first_occupied, passed_voxels

MIN_RANGE = 1.0   # metres from the sensor: closer returns are not counted (nuScenes devkit remove_close)


def frame_rays(points_ego: np.ndarray, origin, range_min, range_max, min_range: float = MIN_RANGE):
    """The counted returns: (M, 3) unit directions, (M,) measured depths, (M, 3) points; see the module doc."""
    p = np.asarray(points_ego, np.float64)[:, :3]
    o = np.asarray(origin, np.float64).reshape(3)
    inside = np.all((p >= np.asarray(range_min)) & (p < np.asarray(range_max)), axis=1)
    v = p - o
    dist = np.linalg.norm(v, axis=1)
    keep = inside & (dist >= min_range)
    return v[keep] / dist[keep, None], dist[keep], p[keep]


def score_frame(occupied: np.ndarray, range_min, voxel_size, points_ego: np.ndarray, origin,
                min_range: float = MIN_RANGE) -> dict:
    """The three measures of one frame, as counts and the per-ray depth errors (see the module doc)."""
    occ = np.asarray(occupied, bool)
    shape = np.asarray(occ.shape)
    rmin = np.asarray(range_min, np.float64)
    vs = np.asarray(voxel_size, np.float64)
    rmax = rmin + vs * shape
    dirs, depth, pts = frame_rays(points_ego, origin, rmin, rmax, min_range)
    pred_depth, _ = first_occupied(occ, rmin, vs, origin, dirs)
    no_hit = ~np.isfinite(pred_depth)
    pred_depth = np.where(no_hit, exit_distance(rmin, rmax, origin, dirs), pred_depth)
    passed, return_entry = passed_voxels(occ.shape, rmin, vs, origin, dirs, depth)
    return_entry = np.where(np.isfinite(return_entry), return_entry, depth)   # (rounding at the grid's edge)
    errors = np.abs(pred_depth - return_entry)

    idx = np.clip(np.floor((pts - rmin) / vs).astype(np.int64), 0, shape - 1)
    point_flat = (idx[:, 0] * shape[1] + idx[:, 1]) * shape[2] + idx[:, 2]
    hit_flat = np.unique(point_flat)
    flat_occ = occ.ravel()
    seen_free = np.setdiff1d(passed, hit_flat, assume_unique=True)
    return {
        "rays": int(len(depth)),
        "depth_errors": errors.astype(np.float32),
        "no_hit": int(no_hit.sum()),
        "returns_in_occupied": int(flat_occ[point_flat].sum()),
        "occupied_voxels": int(flat_occ.sum()),
        "occupied_seen_free": int(flat_occ[seen_free].sum()),
        "seen_free_voxels": int(len(seen_free)),
    }


def _share(a: float, b: float) -> float | None:
    return None if b == 0 else round(100.0 * a / b, 2)


def measures(counts: dict) -> dict:
    """Per-frame or pooled counts -> the reported numbers (metres; shares in percent; None when undefined)."""
    e = counts["depth_errors"]
    return {
        "rays": counts["rays"],
        "depth_error_mean_m": None if not len(e) else round(float(e.mean()), 3),
        "depth_error_median_m": None if not len(e) else round(float(np.median(e)), 3),
        "depth_error_under_1m_pct": _share(float((e < 1.0).sum()), len(e)),
        "rays_no_occupied_pct": _share(counts["no_hit"], counts["rays"]),
        "lidar_hits_in_occupied_pct": _share(counts["returns_in_occupied"], counts["rays"]),
        "occupied_voxels": counts["occupied_voxels"],
        "occupied_seen_free_pct": _share(counts["occupied_seen_free"], counts["occupied_voxels"]),
    }


class LidarAgreement:
    """Per-frame scores and the pooled total over frames."""

    def __init__(self):
        self.frames: list[tuple[str, dict]] = []

    def update(self, name: str, counts: dict) -> None:
        self.frames.append((name, counts))

    def pooled(self) -> dict:
        keys = ("rays", "no_hit", "returns_in_occupied", "occupied_voxels", "occupied_seen_free", "seen_free_voxels")
        total = {k: sum(c[k] for _, c in self.frames) for k in keys}
        total["depth_errors"] = (np.concatenate([c["depth_errors"] for _, c in self.frames])
                                 if self.frames else np.zeros(0, np.float32))
        return total

    def summary(self) -> dict:
        return {"frames": len(self.frames), "min_range_m": MIN_RANGE, "overall": measures(self.pooled()),
                "per_frame": {name: measures(c) for name, c in self.frames}}

    def to_markdown(self) -> str:
        cols = ("depth_error_mean_m", "depth_error_median_m", "depth_error_under_1m_pct", "rays_no_occupied_pct",
                "lidar_hits_in_occupied_pct", "occupied_seen_free_pct")
        head = ("| frame | rays | depth error mean (m) | median (m) | under 1 m (%) | rays meeting no occupied (%) "
                "| LiDAR hits in occupied (%) | occupied seen free (%) |")
        lines = [head, "|---|---:|---:|---:|---:|---:|---:|---:|"]

        def row(name, m):
            vals = ["n/a" if m[c] is None else f"{m[c]}" for c in cols]
            return f"| {name} | {m['rays']} | " + " | ".join(vals) + " |"

        for name, c in self.frames:
            lines.append(row(name, measures(c)))
        lines.append(row("**overall**", measures(self.pooled())))
        lines.append("")
        lines.append(f"{len(self.frames)} frame(s); rays = keyframe LiDAR returns inside the grid and >= {MIN_RANGE} m "
                     "from the sensor. Lower is better for depth error, rays meeting nothing and occupied seen free; "
                     "higher for hits in occupied (docs/metric_and_pictures.md).")
        return "\n".join(lines) + "\n"
