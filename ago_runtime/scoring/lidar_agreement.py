"""How well a predicted occupancy agrees with a keyframe's real LiDAR, beside predictors that see no image.

Inputs per frame (`frame_truth`): the keyframe's LiDAR returns in the ego frame ((N, 3) metres), the LiDAR
origin there (lidar2ego's translation), the grid (shape, `range_min`, `voxel_size`), and per return its
object class ("" for none: the class of the annotated box it lies in, chosen by the caller, e.g.
`ago_runtime.formats.nuscenes_boxes.return_classes`) and whether it is ground (`ground_returns`: below
0.3 m in the ego frame and in no box). Which returns count: those inside the grid and at least
`MIN_RANGE` (1 m) from the sensor (the nuScenes devkit's `remove_close`). Each counted return is one
ray, origin -> return.

Per ray, the prediction's depth is where the ray enters its first predicted-occupied voxel
(`rays.first_occupied`) and its class is that voxel's; the return's depth is where the ray enters the
voxel holding the return (`rays.passed_voxels`), so a prediction whose first occupied voxel is the
return's own scores depth error 0. A ray is right at tau (1, 2, 4 m) when it meets an occupied voxel
and |predicted depth - return depth| < tau.

Primary measures (pooled over frames: counts are summed, then divided):
- object ray IoU: per object class c (the classes a box can give) and tau, TP_c = rays whose return has
  class c, right at tau, whose first hit has class c; GT_c = rays whose return has class c; P_c = rays
  (any return) whose first hit has class c. IoU_c = TP_c / (GT_c + P_c - TP_c); NaN (left out) when
  GT_c + P_c = 0. Mean over classes per tau, then over the three taus.
- geometry ray IoU, ground and non-ground returns apart: over the rays of that part, TP = rays right at
  tau (class not asked), GT = the rays, P = the rays meeting an occupied voxel: TP / (GT + P - TP).
  A ray that meets an occupied voxel at the wrong depth counts twice (a false positive where it
  stopped and a false negative at its return), as in RayIoU.
- voxel precision, recall, F1 over judged voxels only: occupied = holds a counted return; free = some
  ray left it before reaching its return and it holds none; every other voxel is unjudged.
  precision = TP / (TP + FP), recall = TP / (TP + FN), F1 = 2 TP / (2 TP + FP + FN).
Diagnostics (the first measures, kept to compare with older results): depth error (a ray meeting no
occupied voxel gets the distance at which it leaves the grid), rays meeting none, returns whose voxel is
predicted occupied, predicted-occupied voxels some ray saw through (over all predicted-occupied voxels).

Blind spots: the space behind a return is never judged (a prediction may fill it for free); only one
sweep per keyframe (no non-key sweeps), so thin or far matter has few rays; classes come from boxes only.

No-image predictors (`baseline_volumes`) are scored with the same rays in the same pass: all free, all
occupied, ground slabs (voxel centre z < 0.2 m; < 0.6 m), the bowl (voxel centre z < 0.2 m; z < 0.6 m
where the centre's horizontal distance from the ego origin is more than 6 m; every height beyond 30 m),
and, when given, a training-frame prior (`TrainingPrior`: each voxel's most frequent pseudo-label over
the training keyframes, in the ego frame). `score_with_baselines` runs it all over a list of frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

from ago_runtime.scoring.rays import exit_distance, first_occupied, passed_voxels

MIN_RANGE = 1.0   # metres from the sensor: closer returns are not counted (nuScenes devkit remove_close)
THRESHOLDS = (1.0, 2.0, 4.0)
PREDICTION = "prediction"
BASELINES = {
    "all_free": "every voxel free",
    "all_occupied": "every voxel occupied (no class)",
    "slab_0.2": "occupied iff the voxel centre's z < 0.2 m",
    "slab_0.6": "occupied iff the voxel centre's z < 0.6 m",
    "bowl": "occupied iff centre z < 0.2 m, or z < 0.6 m with the centre more than 6 m from the ego origin "
            "horizontally, or the centre more than 30 m from it (every height)",
    "prior": "each voxel's most frequent pseudo-label over the training keyframes (ego frame; ties -> free)",
}
# the primary measures, in the order reports list them, and which way is better (all: higher)
PRIMARY = ("object_ray_iou", "geometry_ray_iou_nonground@1", "geometry_ray_iou_nonground@2",
           "geometry_ray_iou_nonground@4", "voxel_f1_pct")
DIAGNOSTICS = ("depth_error_mean_m", "depth_error_median_m", "depth_error_under_1m_pct", "rays_no_occupied_pct",
               "lidar_hits_in_occupied_pct", "occupied_seen_free_pct")


@dataclass
class FrameTruth:
    """What the LiDAR of one keyframe says, on one grid: every counted ray and the judged voxels."""
    name: str
    shape: tuple[int, int, int]
    range_min: np.ndarray
    voxel_size: np.ndarray
    origin: np.ndarray
    dirs: np.ndarray            # (M, 3) unit directions
    return_depth: np.ndarray    # (M,) where the ray enters the voxel holding its return
    grid_exit: np.ndarray       # (M,) where the ray leaves the grid
    return_voxel: np.ndarray    # (M,) flat index of the return's voxel
    ray_class: np.ndarray       # (M,) index into the object classes; len(classes) = not an object
    ground: np.ndarray          # (M,) bool
    occupied_voxels: np.ndarray  # flat indices holding a return (sorted, unique)
    free_voxels: np.ndarray      # flat indices some ray crossed before its return, holding none


def frame_rays(points_ego: np.ndarray, origin, range_min, range_max, min_range: float = MIN_RANGE):
    """The counted returns: (M, 3) unit directions, (M,) measured depths, (M,) bool keep mask over the points."""
    p = np.asarray(points_ego, np.float64)[:, :3]
    o = np.asarray(origin, np.float64).reshape(3)
    inside = np.all((p >= np.asarray(range_min)) & (p < np.asarray(range_max)), axis=1)
    v = p - o
    dist = np.linalg.norm(v, axis=1)
    keep = inside & (dist >= min_range)
    return v[keep] / dist[keep, None], dist[keep], keep


def frame_truth(name: str, points_ego: np.ndarray, origin, shape, range_min, voxel_size,
                object_classes: Sequence[str] = (), point_classes: np.ndarray | None = None,
                ground: np.ndarray | None = None, min_range: float = MIN_RANGE) -> FrameTruth:
    """The rays and judged voxels of one keyframe (see the module doc). `point_classes` (N,) names each
    return's object class ("" or a name not in `object_classes`: none); `ground` (N,) bool marks ground
    returns (default: none)."""
    shape = tuple(int(s) for s in shape)
    rmin = np.asarray(range_min, np.float64)
    vs = np.asarray(voxel_size, np.float64)
    rmax = rmin + vs * np.asarray(shape)
    o = np.asarray(origin, np.float64).reshape(3)
    pts = np.asarray(points_ego, np.float64)[:, :3]
    dirs, depth, keep = frame_rays(pts, o, rmin, rmax, min_range)
    n_cls = len(object_classes)
    index = {c: i for i, c in enumerate(object_classes)}
    cls = np.full(len(pts), n_cls, np.int64)
    if point_classes is not None:
        cls = np.array([index.get(c, n_cls) for c in np.asarray(point_classes, object)], np.int64).reshape(len(pts))
    gnd = np.zeros(len(pts), bool) if ground is None else np.asarray(ground, bool).reshape(len(pts))
    passed, entry = passed_voxels(shape, rmin, vs, o, dirs, depth)
    entry = np.where(np.isfinite(entry), entry, depth)   # (rounding at the grid's edge)
    idx = np.clip(np.floor((pts[keep] - rmin) / vs).astype(np.int64), 0, np.asarray(shape) - 1)
    flat = (idx[:, 0] * shape[1] + idx[:, 1]) * shape[2] + idx[:, 2]
    occupied = np.unique(flat)
    return FrameTruth(name, shape, rmin, vs, o, dirs, entry, exit_distance(rmin, rmax, o, dirs), flat,
                      cls[keep], gnd[keep], occupied, np.setdiff1d(passed, occupied, assume_unique=True))


def score_frame_counts(truth: FrameTruth, occupied: np.ndarray, objects: np.ndarray | None, n_classes: int,
                       thresholds: Sequence[float] = THRESHOLDS) -> dict:
    """Counts of one predictor on one frame. `occupied` (X, Y, Z) bool; `objects` (X, Y, Z) int: each voxel's
    object class index (n_classes = not an object; None: no voxel has one)."""
    occ = np.asarray(occupied, bool)
    if occ.shape != truth.shape:
        raise ValueError(f"prediction shape {occ.shape} != the frame's grid {truth.shape}")
    depth, voxel = first_occupied(occ, truth.range_min, truth.voxel_size, truth.origin, truth.dirs)
    hit = voxel >= 0
    pclass = np.full(len(voxel), n_classes, np.int64)
    if objects is not None:
        pclass[hit] = np.asarray(objects).ravel()[voxel[hit]]
    err = np.abs(np.where(hit, depth, truth.grid_exit) - truth.return_depth)
    right = np.stack([hit & (err < t) for t in thresholds])          # (T, M)
    k = n_classes + 1
    same = pclass == truth.ray_class
    parts = np.stack([truth.ground, ~truth.ground])                  # (2, M): ground, non-ground
    flat = occ.ravel()
    tp_vox = int(flat[truth.occupied_voxels].sum())
    fp_vox = int(flat[truth.free_voxels].sum())       # predicted occupied where a ray saw through
    return {
        "rays": int(len(voxel)),
        "object_gt": np.bincount(truth.ray_class, minlength=k)[:n_classes],
        "object_pred": np.bincount(pclass, minlength=k)[:n_classes],
        "object_tp": np.stack([np.bincount(truth.ray_class[r & same], minlength=k)[:n_classes] for r in right]),
        "part_rays": parts.sum(axis=1),
        "part_hit": (parts & hit).sum(axis=1),
        "part_tp": np.stack([(parts & r).sum(axis=1) for r in right]),  # (T, 2)
        "voxel_tp": tp_vox,
        "voxel_fn": int(len(truth.occupied_voxels)) - tp_vox,
        "voxel_fp": fp_vox,
        "judged_free": int(len(truth.free_voxels)),
        "depth_errors": err.astype(np.float32),
        "no_hit": int((~hit).sum()),
        "returns_in_occupied": int(flat[truth.return_voxel].sum()),
        "occupied_voxels": int(flat.sum()),
        "occupied_seen_free": fp_vox,
    }


def _pct(a: float, b: float) -> float | None:
    return None if b == 0 else round(100.0 * a / b, 2)


def _iou_pct(tp, gt, pred) -> np.ndarray:
    union = np.asarray(gt) + np.asarray(pred) - np.asarray(tp)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(union > 0, 100.0 * np.asarray(tp) / np.where(union > 0, union, 1), np.nan)


def _num(x) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x), 2)


def pool(counts: Sequence[dict]) -> dict:
    """Counts of several frames summed (depth errors concatenated)."""
    out = {}
    for key in counts[0]:
        vals = [c[key] for c in counts]
        out[key] = np.concatenate(vals) if key == "depth_errors" else sum(vals[1:], vals[0])
    return out


def measures(counts: dict, object_classes: Sequence[str] = (), thresholds: Sequence[float] = THRESHOLDS) -> dict:
    """Per-frame or pooled counts -> the reported numbers (IoUs and shares in percent, None when undefined)."""
    out: dict = {"rays": counts["rays"], "object_rays": int(np.sum(counts["object_gt"])),
                 "ground_rays": int(counts["part_rays"][0]), "nonground_rays": int(counts["part_rays"][1])}
    obj = _iou_pct(counts["object_tp"], counts["object_gt"][None], counts["object_pred"][None])   # (T, C)
    at = [np.nanmean(r) if np.any(np.isfinite(r)) else np.nan for r in obj]
    out["object_ray_iou"] = _num(np.mean(at)) if all(np.isfinite(at)) else None
    for t, v in zip(thresholds, at):
        out[f"object_ray_iou@{t:g}"] = _num(v)
    out["object_ray_iou_per_class"] = {c: {f"@{t:g}": _num(obj[i, j]) for i, t in enumerate(thresholds)}
                                       for j, c in enumerate(object_classes)}
    geo = _iou_pct(counts["part_tp"], counts["part_rays"][None], counts["part_hit"][None])        # (T, 2)
    for j, part in enumerate(("ground", "nonground")):
        for i, t in enumerate(thresholds):
            out[f"geometry_ray_iou_{part}@{t:g}"] = _num(geo[i, j])
        out[f"geometry_ray_iou_{part}"] = _num(np.mean(geo[:, j])) if np.all(np.isfinite(geo[:, j])) else None
    tp, fp, fn = counts["voxel_tp"], counts["voxel_fp"], counts["voxel_fn"]
    out.update({"voxel_precision_pct": _pct(tp, tp + fp), "voxel_recall_pct": _pct(tp, tp + fn),
                "voxel_f1_pct": _pct(2 * tp, 2 * tp + fp + fn), "judged_occupied_voxels": tp + fn,
                "judged_free_voxels": counts["judged_free"]})
    e = counts["depth_errors"]
    out.update({
        "depth_error_mean_m": None if not len(e) else round(float(e.mean()), 3),
        "depth_error_median_m": None if not len(e) else round(float(np.median(e)), 3),
        "depth_error_under_1m_pct": _pct(float((e < 1.0).sum()), len(e)),
        "rays_no_occupied_pct": _pct(counts["no_hit"], counts["rays"]),
        "lidar_hits_in_occupied_pct": _pct(counts["returns_in_occupied"], counts["rays"]),
        "occupied_voxels": counts["occupied_voxels"],
        "occupied_seen_free_pct": _pct(counts["occupied_seen_free"], counts["occupied_voxels"]),
    })
    return out


# ------------------------------------------------------------------------------------ no-image predictors
def voxel_centres(shape, range_min, voxel_size) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ego-frame x, y, z of every voxel centre, broadcastable to (X, Y, Z)."""
    rmin = np.asarray(range_min, np.float64)
    vs = np.asarray(voxel_size, np.float64)
    x, y, z = (rmin[a] + vs[a] * (np.arange(shape[a]) + 0.5) for a in range(3))
    return x[:, None, None], y[None, :, None], z[None, None, :]


def baseline_volumes(shape, range_min, voxel_size) -> dict[str, np.ndarray]:
    """The occupancy (X, Y, Z) bool of each no-image predictor but the prior (see BASELINES)."""
    shape = tuple(int(s) for s in shape)
    x, y, z = voxel_centres(shape, range_min, voxel_size)
    r = np.hypot(x, y)
    full = np.ones(shape, bool)
    return {
        "all_free": np.zeros(shape, bool),
        "all_occupied": full,
        "slab_0.2": full & (z < 0.2),
        "slab_0.6": full & (z < 0.6),
        "bowl": full & ((z < 0.2) | ((z < 0.6) & (r > 6.0)) | (r > 30.0)),
    }


def object_volume(labels: np.ndarray, class_names: Sequence[str], object_classes: Sequence[str]) -> np.ndarray:
    """(X, Y, Z) int64: each voxel's object class index (len(object_classes): not an object), from labels that
    index `class_names` (any label outside them, e.g. free or 255, is not an object)."""
    index = {c: i for i, c in enumerate(object_classes)}
    lut = np.full(256, len(object_classes), np.int64)
    for i, c in enumerate(class_names[:256]):
        lut[i] = index.get(c, len(object_classes))
    return lut[np.asarray(labels).astype(np.int64).clip(0, 255)]


class TrainingPrior:
    """Each voxel's most frequent label over the pseudo-labels added (ego frame, one grid): `add` each training
    keyframe's labels (0..K-1 classes, `free_index`, 255 unlabelled: not counted), then `labels()` gives the
    mode; ties go to free, and a voxel never labelled is free."""

    def __init__(self, class_names: Sequence[str], free_index: int, shape):
        self.class_names = list(class_names)
        self.free_index = int(free_index)
        self.shape = tuple(int(s) for s in shape)
        self.counts = np.zeros((int(np.prod(self.shape)), len(self.class_names) + 1), np.uint16)  # free last
        self.frames = 0

    def add(self, labels: np.ndarray) -> None:
        lab = np.asarray(labels).astype(np.int64).ravel()
        if np.asarray(labels).shape != self.shape:
            raise ValueError(f"pseudo-label shape {np.asarray(labels).shape} != {self.shape}")
        k = len(self.class_names)
        col = np.where(lab == self.free_index, k, lab)
        ok = (col >= 0) & (col <= k) & ((lab < k) | (lab == self.free_index))
        np.add.at(self.counts, (np.flatnonzero(ok), col[ok]), 1)
        self.frames += 1

    def labels(self) -> np.ndarray:
        """(X, Y, Z) int64: class index 0..K-1 or `free_index`."""
        k = len(self.class_names)
        order = np.concatenate([[k], np.arange(k)])          # free first, so a tie goes to free
        best = order[np.argmax(self.counts[:, order], axis=1)]
        return np.where(best == k, self.free_index, best).reshape(self.shape)


# ------------------------------------------------------------------------------------ the report
class LidarReport:
    """Per-frame counts of the prediction and of every no-image predictor; pooled measures and a markdown table."""

    def __init__(self, object_classes: Sequence[str], prior: "TrainingPrior | None" = None,
                 thresholds: Sequence[float] = THRESHOLDS):
        self.object_classes = list(object_classes)
        self.thresholds = tuple(float(t) for t in thresholds)
        self.prior = prior
        if prior is not None:
            self.prior_labels = prior.labels()
            self.prior_objects = object_volume(self.prior_labels, prior.class_names, self.object_classes)
        self.frames: list[str] = []
        self.counts: dict[str, list[dict]] = {}
        self.notes: list[str] = []
        self._measures: dict[str, dict] | None = None

    @property
    def predictors(self) -> list[str]:
        return [PREDICTION] + [b for b in BASELINES if b != "prior" or self.prior is not None]

    def update(self, truth: FrameTruth, occupied: np.ndarray, objects: np.ndarray | None) -> None:
        """Score one frame's prediction (occupancy and object class volume) and every baseline on its grid."""
        n = len(self.object_classes)
        volumes = {PREDICTION: (occupied, objects)}
        volumes.update({k: (v, None) for k, v in baseline_volumes(truth.shape, truth.range_min,
                                                                   truth.voxel_size).items()})
        if self.prior is not None:
            volumes["prior"] = self.prior_on(truth.shape)
        for name, (occ, obj) in volumes.items():
            self.counts.setdefault(name, []).append(score_frame_counts(truth, occ, obj, n, self.thresholds))
        self.frames.append(truth.name)
        self._measures = None

    def prior_on(self, shape) -> tuple[np.ndarray, np.ndarray]:
        """The prior's occupancy and object volume brought to `shape` (an integer multiple of its own)."""
        lab, obj = self.prior_labels, self.prior_objects
        factors = [s // p if p and s % p == 0 else 0 for s, p in zip(shape, lab.shape)]
        if 0 in factors:
            raise ValueError(f"prior grid {lab.shape} does not divide the prediction's grid {tuple(shape)}")
        for a, f in enumerate(factors):
            lab, obj = np.repeat(lab, f, axis=a), np.repeat(obj, f, axis=a)
        return lab != self.prior.free_index, obj

    def all_measures(self) -> dict[str, dict]:
        """Predictor -> its pooled measures (`measures`)."""
        if self._measures is None:
            self._measures = {p: measures(pool(self.counts[p]), self.object_classes, self.thresholds)
                              for p in self.predictors}
        return self._measures

    def beaten(self) -> dict[str, list[str]]:
        """Primary measure -> the baselines that score higher than the prediction on it."""
        m = self.all_measures()
        mine = m[PREDICTION]
        return {key: [b for b in self.predictors[1:] if m[b][key] is not None
                      and (mine[key] is None or m[b][key] > mine[key])] for key in PRIMARY}

    def summary(self) -> dict:
        """JSON-able: see docs/metric_and_pictures.md ("LiDAR measures") for the schema."""
        m = self.all_measures() if self.frames else {}
        return {
            "frames": len(self.frames), "min_range_m": MIN_RANGE, "thresholds_m": list(self.thresholds),
            "object_classes": self.object_classes, "primary": list(PRIMARY), "diagnostics": list(DIAGNOSTICS),
            "baselines": {b: BASELINES[b] for b in self.predictors[1:]},
            "prior_frames": None if self.prior is None else self.prior.frames,
            "predictors": m,
            "beaten_by": self.beaten() if self.frames else {},
            "overall": m.get(PREDICTION),
            "per_frame": {name: measures(self.counts[PREDICTION][i], self.object_classes, self.thresholds)
                          for i, name in enumerate(self.frames)},
            "notes": list(self.notes),
        }

    def to_markdown(self) -> str:
        def cell(v):
            return "n/a" if v is None else f"{v}"

        rows = self.all_measures()
        t = [f"{x:g}" for x in self.thresholds]
        lines = ["| predictor | object ray IoU (%) | " + " | ".join(f"non-ground ray IoU @{x} m" for x in t)
                 + " | voxel F1 (%) | voxel precision | voxel recall | " + " | ".join(f"ground ray IoU @{x} m" for x in t)
                 + " |", "|---|" + "---:|" * (4 + 2 * len(t))]
        for p, m in rows.items():
            lines.append(f"| {p} | {cell(m['object_ray_iou'])} | "
                         + " | ".join(cell(m[f'geometry_ray_iou_nonground@{x}']) for x in t)
                         + f" | {cell(m['voxel_f1_pct'])} | {cell(m['voxel_precision_pct'])} | "
                         f"{cell(m['voxel_recall_pct'])} | "
                         + " | ".join(cell(m[f'geometry_ray_iou_ground@{x}']) for x in t) + " |")
        m0 = rows[PREDICTION]
        prior = "" if self.prior is None else f" (prior over {self.prior.frames} training keyframes)"
        lines += ["", f"{len(self.frames)} frame(s); {m0['rays']} rays (returns inside the grid, >= {MIN_RANGE} m from "
                  f"the sensor): {m0['object_rays']} in an object box, {m0['ground_rays']} ground, "
                  f"{m0['nonground_rays']} non-ground; {m0['judged_occupied_voxels']} judged-occupied and "
                  f"{m0['judged_free_voxels']} judged-free voxels. All higher is better (docs/metric_and_pictures.md). "
                  "Baselines see no image: " + "; ".join(f"{b} = {BASELINES[b]}" for b in self.predictors[1:])
                  + prior + ".", ""]
        names = {"object_ray_iou": "object ray IoU", "voxel_f1_pct": "voxel F1"}
        worse = [f"{names.get(k, 'non-ground ray IoU @' + k.rsplit('@', 1)[-1] + ' m')}: {', '.join(v)}"
                 for k, v in self.beaten().items() if v]
        lines.append("**Baselines that beat the prediction**: " + ("; ".join(worse) if worse else "none") + ".")
        lines += ["", "Per-class object ray IoU (%) of the prediction:", "",
                  "| class | " + " | ".join(f"@{x} m" for x in t) + " |", "|---|" + "---:|" * len(t)]
        for c, v in m0["object_ray_iou_per_class"].items():
            if any(val is not None for val in v.values()):
                lines.append(f"| {c} | " + " | ".join(cell(v[f'@{x}']) for x in t) + " |")
        lines += ["", "Diagnostics (the first LiDAR measures; a constant can score well on them):", "",
                  "| predictor | depth error mean (m) | median (m) | under 1 m (%) | rays meeting no occupied (%) "
                  "| LiDAR hits in occupied (%) | occupied seen free (%) |", "|---|---:|---:|---:|---:|---:|---:|"]
        for p, m in rows.items():
            lines.append(f"| {p} | " + " | ".join(cell(m[c]) for c in DIAGNOSTICS) + " |")
        if self.notes:
            lines += [""] + [f"Note: {n}" for n in self.notes]
        return "\n".join(lines) + "\n"


def score_with_baselines(frames: Iterable[tuple[FrameTruth, np.ndarray, np.ndarray | None]],
                         object_classes: Sequence[str], prior: TrainingPrior | None = None) -> dict:
    """Score (truth, occupied, object volume) frames and every no-image baseline; `LidarReport.summary()`."""
    report = LidarReport(object_classes, prior)
    for truth, occupied, objects in frames:
        report.update(truth, occupied, objects)
    return report.summary()


def score_frame(occupied: np.ndarray, range_min, voxel_size, points_ego: np.ndarray, origin,
                min_range: float = MIN_RANGE) -> dict:
    """Counts of one occupancy volume on one frame with no classes and no ground (a short form for tests)."""
    occ = np.asarray(occupied, bool)
    truth = frame_truth("frame", points_ego, origin, occ.shape, range_min, voxel_size, min_range=min_range)
    return score_frame_counts(truth, occ, None, 0)

