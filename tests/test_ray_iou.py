"""RayIoU as SparseOcc computes it (issue 46): ray origins from the scene's LiDAR poses, checked against a
separate, deliberately simple implementation written here: origins worked out from the poses in SparseOcc's
own order of transforms (global -> reference LiDAR -> reference ego), the |x|, |y| < 39 m filter and the 8-origin
pick as plain loops, and rays marched in 2 cm steps through the volume, the depth being where the ray leaves
the first occupied voxel (that voxel's box, by the slab method)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from ago_runtime.classes import FREE, OCC3D_CLASSES
from ago_runtime.geometry.grid import Grid
from ago_runtime.scoring.ray_iou import RayIoU, lidar_like_rays, scene_origins

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_bad_inputs import assert_one_error_line, run_ago  # noqa: E402

GRID = Grid.occ3d()
LO, VS = np.asarray(GRID.range_min, float), np.asarray(GRID.voxel_size, float)
CAR, MANMADE, ROAD = OCC3D_CLASSES.index("car"), OCC3D_CLASSES.index("manmade"), OCC3D_CLASSES.index("driveable_surface")


def pose(x, y, yaw, z=0.0):
    m = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = [x, y, z]
    return m


# ------------------------------------------------------------------------------------ the reference
def reference_origins(ref: int, ego2global: list, lidar2ego: list) -> np.ndarray:
    """SparseOcc's EgoPoseDataset, written out: every frame's LiDAR origin into the reference LiDAR frame via the
    global frame, then into the reference ego frame; keep |x|, |y| < 39; more than 8 -> round(linspace)."""
    ref_lidar_from_global = np.linalg.inv(ego2global[ref] @ lidar2ego[ref])
    kept = []
    for j in range(len(ego2global)):
        if j == ref:
            in_ref_lidar = np.zeros(3)
        else:
            in_ref_lidar = (ref_lidar_from_global @ ego2global[j] @ lidar2ego[j])[:3, 3]
        o = lidar2ego[ref][:3, :3] @ in_ref_lidar + lidar2ego[ref][:3, 3]
        if abs(o[0]) < 39 and abs(o[1]) < 39:
            kept.append(o)
    if len(kept) > 8:
        picks = np.linspace(0, len(kept) - 1, 8)
        kept = [kept[int(round(p))] for p in picks]
    return np.array(kept)


def march(sem: np.ndarray, origin: np.ndarray, dirs: np.ndarray, step: float = 0.02, max_t: float = 120.0):
    """First non-free voxel along each ray by 2 cm steps: (class or FREE, where the ray leaves that voxel)."""
    t = np.arange(step / 2, max_t, step)
    labels, depths = np.full(len(dirs), FREE), np.full(len(dirs), np.inf)
    shape = np.array(sem.shape)
    for r, d in enumerate(dirs):
        idx = np.floor((origin + t[:, None] * d - LO) / VS).astype(int)
        inside = np.all((idx >= 0) & (idx < shape), axis=1)
        stop = np.flatnonzero(~inside)
        idx = idx[: stop[0] if len(stop) else len(t)]
        lab = sem[idx[:, 0], idx[:, 1], idx[:, 2]]
        occ = np.flatnonzero(lab != FREE)
        if not len(occ):
            continue
        v = idx[occ[0]]
        labels[r] = lab[occ[0]]
        lo, hi = LO + v * VS, LO + (v + 1) * VS           # the voxel's box: the ray leaves it at the nearest far face
        with np.errstate(divide="ignore", invalid="ignore"):
            far = np.where(d > 0, (hi - origin) / d, np.where(d < 0, (lo - origin) / d, np.inf))
        depths[r] = far.min()
    return labels, depths


def reference_ray_iou(preds, gts, origins_per_frame, dirs, n_classes=FREE):
    """SparseOcc's calc_rayiou over all frames and origins (GT-free rays dropped per origin)."""
    gt_cnt, pred_cnt, tp = np.zeros(n_classes), np.zeros(n_classes), np.zeros((3, n_classes))
    for pred, gt, origins in zip(preds, gts, origins_per_frame):
        for o in origins:
            gl, gd = march(gt, o, dirs)
            pl, pd = march(pred, o, dirs)
            valid = gl != FREE
            gl, gd, pl, pd = gl[valid], gd[valid], pl[valid], pd[valid]
            for c in range(n_classes):
                gt_cnt[c] += (gl == c).sum()
                pred_cnt[c] += (pl == c).sum()
                for j, thr in enumerate((1, 2, 4)):
                    tp[j, c] += ((gl == c) & (pl == c) & (np.abs(pd - gd) < thr)).sum()
    with np.errstate(divide="ignore", invalid="ignore"):
        iou = tp / (gt_cnt + pred_cnt - tp)
    return gt_cnt, pred_cnt, tp, np.nanmean(iou)


# ------------------------------------------------------------------------------------ a moving scene
def scene(n_frames=12):
    """Poses of a car driving ~4.3 m per keyframe while turning, a LiDAR slightly yawed on the roof, and per
    frame GT (a road slab, car and building blocks) and a prediction (blocks shifted or relabelled)."""
    ego2global = [pose(100 + 4.0 * j, 50 + 0.02 * j * j * 4, 0.04 * j, 0.1 * j) for j in range(n_frames)]
    lidar2ego = [pose(0.943, 0.0, 0.01, 1.84)] * n_frames
    rng = np.random.default_rng(0)
    gts, preds = [], []
    for j in range(n_frames):
        gt = np.full(GRID.shape, FREE, np.uint8)
        gt[:, :, :3] = ROAD
        pred = gt.copy()
        for k in range(12):
            i0, j0 = rng.integers(20, 180, 2)
            if abs(i0 - 100) < 8 and abs(j0 - 100) < 8:
                continue
            cls, size = (CAR, (10, 5, 4)) if k % 2 else (MANMADE, (6, 14, 12))
            gt[i0:i0 + size[0], j0:j0 + size[1], 3:3 + size[2]] = cls
            shift = int(rng.integers(-3, 4))
            pred_cls = cls if k % 5 else MANMADE
            pred[i0 + shift:i0 + shift + size[0], j0:j0 + size[1], 3:3 + size[2]] = pred_cls
        pred[:, :, 2][rng.random(GRID.shape[:2]) < 0.1] = FREE      # holes in the predicted road
        gts.append(gt)
        preds.append(pred)
    return ego2global, lidar2ego, gts, preds


def test_scene_origins_match_the_reference():
    ego2global, lidar2ego, _, _ = scene(14)
    poses = list(zip(lidar2ego, ego2global))
    for ref in (0, 5, 13):
        ours = scene_origins(ego2global[ref], poses)
        want = reference_origins(ref, ego2global, lidar2ego)
        np.testing.assert_allclose(ours, want, atol=1e-9)
    # from the first frame the later origins pass 39 m and are dropped; the kept ones are thinned to 8
    near = reference_origins(0, ego2global, lidar2ego)
    assert len(near) == 8 and np.abs(near[:, :2]).max() < 39
    every = [(inv @ e @ l)[:3, 3] for inv in [np.linalg.inv(ego2global[0])] for l, e in poses]
    assert sum(abs(o[0]) < 39 and abs(o[1]) < 39 for o in every) in range(9, 14)
    np.testing.assert_allclose(scene_origins(ego2global[0], poses[:1]), [[0.943, 0.0, 1.84]], atol=1e-12)


def test_ray_iou_matches_the_simple_reference_with_moving_origins():
    ego2global, lidar2ego, gts, preds = scene(12)
    poses = list(zip(lidar2ego, ego2global))
    dirs = lidar_like_rays()[::37]                    # 380 rays of the fan, all pitches and azimuths mixed
    frames = (0, 4, 11)
    names = list(OCC3D_CLASSES)
    m = RayIoU(names, FREE, directions=dirs)
    origins = []
    for j in frames:
        origins.append(reference_origins(j, ego2global, lidar2ego))
        m.update(preds[j], gts[j], GRID.range_min, GRID.voxel_size, scene_origins(ego2global[j], poses))
    assert m.origins_used == sum(len(o) for o in origins) and m.origins_outside_grid == 0
    assert len({tuple(np.round(o[0], 3)) for o in origins}) == 3     # the origins move from frame to frame
    gt_cnt, pred_cnt, tp, ray_iou = reference_ray_iou([preds[j] for j in frames], [gts[j] for j in frames],
                                                      origins, dirs)
    # 2 cm steps miss a voxel a ray clips by less than that (3 of ~4,200 rays here, at the grid's edge), and may
    # put a depth on the other side of a threshold: counts agree to a few rays
    assert m.gt.sum() > 3000 and np.abs(m.gt[:FREE] - gt_cnt).max() <= 4 and (m.gt[:FREE] == gt_cnt).mean() > 0.8
    assert np.abs(m.pred[:FREE] - pred_cnt).max() <= 4 and (m.pred[:FREE] == pred_cnt).mean() > 0.8
    assert np.abs(m.tp[:, :FREE] - tp).max() <= 4
    assert m.ray_iou() == pytest.approx(ray_iou, abs=2e-3)
    assert 0.2 < m.ray_iou() < 0.95
    # one fixed origin gives other numbers: the scene's origins matter
    fixed = RayIoU(names, FREE, directions=dirs)
    for j in frames:
        fixed.update(preds[j], gts[j], GRID.range_min, GRID.voxel_size)
    assert fixed.rays < m.rays and fixed.ray_iou() != pytest.approx(m.ray_iou(), abs=1e-4)


# ------------------------------------------------------------------------------------ ago metric --gt --data
@pytest.fixture(scope="module")
def town(tmp_path_factory):
    root = tmp_path_factory.mktemp("ray_town")
    r = run_ago(["synth", "--out", root / "synth", "--scenes", "1", "--frames", "3", "--image-size", "96x54",
                 "--val-fraction", "0"], root)
    assert r.code == 0, r.stderr
    (root / "pred").mkdir()
    for f in (root / "synth" / "gts").glob("*/*/labels.npz"):
        sem = np.load(f)["semantics"]
        np.savez(root / "pred" / f"{f.parent.name}.npz", semantics=np.roll(sem, 2, axis=0))
    return root


def test_metric_takes_the_origins_from_the_dataroot(town):
    r = run_ago(["metric", "--pred", "pred", "--gt", "synth/gts", "--data", "synth", "--json", "scene.json"], town)
    assert r.code == 0, r.stderr
    s = json.loads((town / "scene.json").read_text())["ray_iou"]
    assert s["origins"] == "scene (SparseOcc)" and s["origin_m"] is None
    assert s["origins_used"] == 9 and s["frames"] == 3           # 3 keyframes, each seeing the scene's 3 origins
    assert "scene origins" in r.stdout and "note:" not in r.stdout + r.stderr
    r = run_ago(["metric", "--pred", "pred", "--gt", "synth/gts", "--json", "fixed.json"], town)
    assert r.code == 0, r.stderr
    f = json.loads((town / "fixed.json").read_text())["ray_iou"]
    assert f["origins"] == "fixed" and f["origins_used"] == 3
    assert "note: RayIoU casts from one fixed origin" in r.stdout + r.stderr
    assert f["rays_counted"] < s["rays_counted"]


def test_metric_data_refusals(town):
    r = run_ago(["metric", "--pred", "pred", "--gt", "synth/gts", "--data", "synth", "--ray-origin", "0,0,1"], town)
    assert_one_error_line(r, "--ray-origin", "--data")
    r = run_ago(["metric", "--pred", "pred", "--lidar", "synth", "--data", "synth"], town)
    assert_one_error_line(r, "--data", "--gt")
    r = run_ago(["metric", "--pred", "pred", "--gt", "synth/gts", "--data", "pred", "--json", "x.json"], town)
    assert_one_error_line(r, "pred", "dataroot")
    assert not (town / "x.json").exists()
