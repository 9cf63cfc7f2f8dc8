"""Real camera data end to end (issue 35): ray casting, RayIoU, the LiDAR measures, `ago metric --lidar`,
and the refusals a user with a real dataroot meets. Tests on ../shared skip when it is absent."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ago_runtime.classes import FREE
from ago_runtime.scoring.lidar_agreement import MIN_RANGE, measures, score_frame
from ago_runtime.scoring.ray_iou import RayIoU, lidar_like_rays
from ago_runtime.scoring.rays import first_occupied, passed_voxels
from conftest import shared_path
from test_bad_inputs import assert_one_error_line, run_ago

RMIN, VS = np.array([-8.0, -8.0, -1.0]), np.array([0.4, 0.4, 0.4])


def dense_first_hit(occ, origin, direction, step=0.001, max_t=40.0):
    """Independent reference: march in 1 mm steps, the first sample inside an occupied voxel (inf: none)."""
    t = np.arange(0.0, max_t, step)
    p = np.asarray(origin) + t[:, None] * direction
    idx = np.floor((p - RMIN) / VS).astype(int)
    inside = np.all((idx >= 0) & (idx < occ.shape), axis=1)
    end = np.flatnonzero(~inside)
    end = end[0] if len(end) else len(t)
    hit = np.flatnonzero(occ[idx[:end, 0], idx[:end, 1], idx[:end, 2]])
    return t[hit[0]] if len(hit) else np.inf


def test_first_occupied_matches_dense_marching():
    rng = np.random.default_rng(0)
    occ = rng.random((40, 40, 10)) < 0.05
    origin = np.array([0.13, -0.07, 0.84])
    occ[tuple(np.floor((origin - RMIN) / VS).astype(int))] = False
    dirs = rng.normal(size=(60, 3))
    dirs[:4] = [[1, 0, 0], [0, -1, 0], [0, 0, 1], [1, 1, 0]]       # axis-aligned and diagonal rays too
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    depth, voxel = first_occupied(occ, RMIN, VS, origin, dirs)
    for d, got, v in zip(dirs, depth, voxel):
        want = dense_first_hit(occ, origin, d)
        if np.isinf(want):
            assert np.isinf(got) and v == -1
        else:
            assert abs(got - want) < 2e-3
            assert occ.ravel()[v]
    assert np.isfinite(depth).sum() > 20   # the random grid is hit by most rays


def test_passed_voxels_stop_before_the_return():
    occ_shape = (40, 40, 10)
    origin = np.array([0.2, 0.2, 0.2])                 # centre of voxel (20, 20, 3)
    passed, entry = passed_voxels(occ_shape, RMIN, VS, origin, [[1.0, 0, 0]], [1.0])
    # from x = 0.2 to 1.2: leaves voxels i = 20 (x 0..0.4) and 21 (0.4..0.8), ends in 22 (entered at 0.6 m)
    assert [np.unravel_index(f, occ_shape)[0] for f in passed] == [20, 21]
    assert entry[0] == pytest.approx(0.6)


def wall_rays_expected(x_face, origin, dirs, lo, hi, vs):
    """Analytic: where each ray meets the plane x = x_face, whether that is inside the box, and where it then leaves
    the voxel it entered there (RayIoU's depth: the exit of the first occupied voxel)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(dirs[:, 0] > 0, (x_face - origin[0]) / dirs[:, 0], np.inf)
    p = origin + np.where(np.isfinite(t), t, 0)[:, None] * dirs
    inside = np.isfinite(t) & np.all((p[:, 1:] >= lo[1:]) & (p[:, 1:] <= hi[1:]), axis=1)
    idx = np.floor((p + 1e-9 * dirs - lo) / vs)
    face = lo + (idx + (dirs > 0)) * vs
    with np.errstate(divide="ignore", invalid="ignore"):
        t_exit = np.where(dirs != 0, (face - origin) / dirs, np.inf).min(axis=1)
    return t_exit, inside


def test_ray_iou_against_an_analytic_wall():
    shape = (100, 100, 16)                         # 40 x 40 x 6.4 m at 0.4 m
    lo, vs = np.array([-20.0, -20.0, -1.0]), np.array([0.4, 0.4, 0.4])
    hi = lo + vs * shape
    gt = np.full(shape, FREE, np.uint8)
    pred = gt.copy()
    gt[75, :, :] = 4        # a car wall whose face is at x = 10 m
    pred[77, :, :] = 4      # predicted 0.8 m further
    names = [str(i) for i in range(FREE + 1)]
    origin = np.array([0.943, 0.0, 1.84])
    m = RayIoU(names, FREE, origin=origin)
    m.update(pred, gt, lo, vs)

    dirs = lidar_like_rays()
    t_gt, hit_gt = wall_rays_expected(10.0, origin, dirs, lo, hi, vs)
    t_pr, hit_pr = wall_rays_expected(10.8, origin, dirs, lo, hi, vs)
    n = hit_gt.sum()
    assert m.rays == n and m.gt[4] == n and m.pred[4] == (hit_gt & hit_pr).sum()
    for i, thr in enumerate((1.0, 2.0, 4.0)):
        tp = (hit_gt & hit_pr & (np.abs(np.where(hit_pr, t_pr, 0) - np.where(hit_gt, t_gt, 0)) < thr)).sum()
        assert m.tp[i, 4] == tp
        assert m.iou()[i, 4] == pytest.approx(tp / (n + m.pred[4] - tp))
    s = m.summary()
    assert 0 < s["RayIoU@1"] < s["RayIoU@2"] <= s["RayIoU@4"]     # 0.8 m off along x: more off along slanted rays
    same = RayIoU(names, FREE, origin=origin)
    same.update(gt, gt, lo, vs)
    assert same.summary()["RayIoU"] == 100.0


@pytest.fixture(scope="module")
def synth_frame():
    from ago_train.synth.config import SynthConfig
    from ago_train.synth.generate import generate_scene

    cfg = SynthConfig(seed=0, num_scenes=1, frames_per_scene=1, image_width=32, image_height=18,
                      grid_shape=(200, 200, 16))
    fr = next(generate_scene(cfg, 0))
    m = fr["lidar2ego"]
    points = fr["lidar_points"][:, :3].astype(np.float64) @ m[:3, :3].T + m[:3, 3]
    return cfg.grid(), fr["gt"].semantics, points, m[:3, 3]


def test_lidar_measures_with_gt_as_prediction(synth_frame):
    grid, sem, points, origin = synth_frame
    occupied = sem != FREE
    gt = measures(score_frame(occupied, grid.range_min, grid.voxel_size, points, origin))
    assert gt["rays"] > 20000
    assert gt["depth_error_median_m"] < 0.4          # within a voxel (0.4 m) on most rays
    assert gt["lidar_hits_in_occupied_pct"] > 85
    assert gt["occupied_seen_free_pct"] < 5
    assert gt["rays_no_occupied_pct"] < 1
    empty = measures(score_frame(np.zeros_like(occupied), grid.range_min, grid.voxel_size, points, origin))
    assert empty["lidar_hits_in_occupied_pct"] == 0 and empty["rays_no_occupied_pct"] == 100
    assert empty["occupied_seen_free_pct"] is None
    noise = np.random.default_rng(0).random(occupied.shape) < occupied.mean()   # as much matter, anywhere
    rand = measures(score_frame(noise, grid.range_min, grid.voxel_size, points, origin))
    assert rand["depth_error_median_m"] > 5 * gt["depth_error_median_m"]
    assert rand["lidar_hits_in_occupied_pct"] < 60 and rand["occupied_seen_free_pct"] > 2 * gt["occupied_seen_free_pct"]


# ------------------------------------------------------------------------------------------ ago metric
def test_metric_reports_both_mious_and_ray_iou(tmp_path, occ3d_sample_labels):
    z = np.load(occ3d_sample_labels)
    sem, cam = z["semantics"], z["mask_camera"].astype(bool)
    pred = np.where(cam, sem, FREE).astype(np.uint8)       # right inside the camera mask, free outside
    (tmp_path / "pred").mkdir()
    np.savez(tmp_path / "pred" / f"{occ3d_sample_labels.parent.name}.npz", semantics=pred)
    r = run_ago(["metric", "--pred", "pred", "--gt", occ3d_sample_labels.parents[2], "--json", "m.json"], tmp_path)
    assert r.code == 0, r.stderr
    s = json.loads((tmp_path / "m.json").read_text())
    assert s["mIoU_camera_mask"] == 100.0 and s["mIoU"] == 100.0
    assert s["mIoU_no_camera_mask"] < 90
    assert 0 < s["ray_iou"]["RayIoU"] < 100 and s["ray_iou"]["rays_counted"] > 5000
    assert "RayIoU" in r.stdout and "no camera mask" in r.stdout


def scene_root() -> Path:
    return shared_path("nuscenes-scene")


def test_metric_lidar_on_the_real_scene(tmp_path):
    from ago_runtime.formats.nuscenes import NuScenesDataset
    from ago_runtime.geometry.grid import Grid

    root = scene_root()
    ds = NuScenesDataset(root, load_images=False, load_extras=False)
    grid = Grid.occ3d()
    (tmp_path / "pred").mkdir()
    for i in (0, 20):
        f = ds[i]
        points = f.lidar.points_in(f.ego2global)
        idx, inside = grid.points_to_index(points)
        inside &= np.linalg.norm(points - f.lidar.lidar2ego[:3, 3], axis=1) >= MIN_RANGE   # the counted returns
        sem = np.full(grid.shape, FREE, np.uint8)
        sem[tuple(idx[inside].T)] = 11                     # the returns' own voxels: right by construction
        np.savez(tmp_path / "pred" / f"{f.token}.npz", semantics=sem)
    np.savez(tmp_path / "pred" / f"{ds.sample_tokens[1]}.npz", semantics=np.full(grid.shape, FREE, np.uint8))
    r = run_ago(["metric", "--pred", "pred", "--lidar", root, "--allow-missing", "--json", "m.json", "--md", "m.md"],
                tmp_path)
    assert r.code == 0, r.stderr
    s = json.loads((tmp_path / "m.json").read_text())["lidar"]
    assert s["frames"] == 3 and len(s["skipped_frames"]) == len(ds) - 3
    full = s["per_frame"][ds.sample_tokens[0]]
    assert full["lidar_hits_in_occupied_pct"] == 100.0 and full["occupied_seen_free_pct"] == 0.0
    assert full["rays"] > 10000
    empty = s["per_frame"][ds.sample_tokens[1]]
    assert empty["lidar_hits_in_occupied_pct"] == 0.0 and empty["rays_no_occupied_pct"] == 100.0
    md = (tmp_path / "m.md").read_text()
    assert "| prediction |" in md and "| bowl |" in md and "Baselines that beat the prediction" in md
    assert set(s["predictors"]) == {"prediction", "all_free", "all_occupied", "slab_0.2", "slab_0.6", "bowl"}


def test_metric_refusals(tmp_path):
    (tmp_path / "pred").mkdir()
    r = run_ago(["metric", "--pred", "pred"], tmp_path)
    assert "--gt" in assert_one_error_line(r, "--lidar")
    r = run_ago(["metric", "--pred", "pred", "--gt", "pred", "--ray-origin", "1,2"], tmp_path)
    assert_one_error_line(r, "--ray-origin")
    r = run_ago(["metric", "--pred", "pred", "--gt", "pred", "--ray-origin", "100,0,1"], tmp_path)
    assert_one_error_line(r, "--ray-origin", "outside")
    root = scene_root()
    r = run_ago(["metric", "--pred", "pred", "--lidar", root / "v1.0-mini", "--json", "m.json"], tmp_path)
    assert_one_error_line(r, "dataroot")
    assert not (tmp_path / "m.json").exists()
    r = run_ago(["metric", "--pred", "pred", "--lidar", root], tmp_path)
    assert_one_error_line(r, "--allow-missing")


# ------------------------------------------------------------------------------------------ boxes segmenter
@pytest.fixture(scope="module")
def scene_frame():
    from ago_runtime.formats.nuscenes import NuScenesDataset

    root = scene_root()
    return root, NuScenesDataset(root, load_images=False, load_extras=False)[0]


def test_boxes_segmenter_paints_a_car_box_centre_car(scene_frame):
    from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file
    from ago_train.pseudo.boxes import BoxSegmenter

    root, frame = scene_frame
    space = parse_prompt_file(resolve_prompt_file("cw"))
    seg = BoxSegmenter(root, space)
    car, ground = space.class_names.index("car"), space.class_names.index("driveable_surface")
    checked = 0
    for cam in frame.rig:
        boxes = seg.frame_boxes(frame)
        centres = np.array([m[:3, 3] for m, _, _ in boxes])
        uv, depth, ok = cam.project(centres)
        # the nearest box whose centre is in view, when it is a car: its centre pixel must be car
        in_view = [i for i in np.flatnonzero(ok) if depth[i] < 30]
        if not in_view:
            continue
        i = min(in_view, key=lambda j: depth[j])
        if boxes[i][2] != "car":
            continue
        labels = seg.segment(frame, cam.name)
        assert labels.shape == (cam.height, cam.width)
        u, v = uv[i].astype(int)
        assert labels[v, u] == car, (cam.name, labels[v, u])
        checked += 1
        assert (labels == ground).mean() > 0.01          # LiDAR ground painted too
        assert (labels == 255).mean() > 0.3               # sky, buildings: no label
    assert checked >= 1


def test_pseudo_labels_boxes_on_the_real_scene(tmp_path):
    root = scene_root()
    r = run_ago(["pseudo-labels", "--data", root, "--out", "pl", "--segmenter", "boxes", "--shard", "41/41",
                 "--keyframes", "2"], tmp_path)
    assert r.code == 0, r.stderr
    assert "note: using shard 41/41: 1 keyframes" in r.stdout and "note: using --embedder none" in r.stdout
    meta = json.loads((tmp_path / "pl" / "meta.json").read_text())
    assert meta["segmenter"]["name"] == "boxes" and "not a VLM" in meta["segmenter"]["config"]["source"]
    files = list((tmp_path / "pl").rglob("labels.npz"))
    assert len(files) == 1
    sem = np.load(files[0])["semantics"]
    assert (sem == 11).sum() > 100        # driveable_surface from the LiDAR ground (cw: class 11)


def test_card_names_boxes_and_an_unaligned_adapter():
    from ago_export.card import summary

    card = {"trained_on": {"kind": "nuscenes", "frames": 30}, "pseudo_labels": {"segmenter": "boxes", "embedder": None},
            "training": {"steps": 10}}
    line = summary(card)
    assert "labels from dataset boxes" in line and "never aligned" in line and "VLM" in line


def test_card_counts_the_default_split():
    from ago_export.card import describe_data

    assert describe_data(str(scene_root()), "train")["frames"] == 30
    assert describe_data(str(scene_root()), "val")["frames"] == 11


# ------------------------------------------------------------------------------------------ splits, shards
def test_default_split_without_splits_json():
    from ago_runtime.errors import AgoInputError
    from ago_runtime.formats.nuscenes import NuScenesDataset

    ds = NuScenesDataset(scene_root(), load_images=False, load_extras=False)
    train, val = ds.split("train"), ds.split("val")
    assert (len(train), len(val)) == (30, 11) and train + val == list(range(41))
    assert "first 3/4" in ds.split_note("train") and "not found" in ds.split_note("val")
    assert ds.split_note("all") is None
    with pytest.raises(AgoInputError, match="write splits.json"):
        ds.split("test")


def test_shards_cover_every_keyframe_once():
    from ago_runtime.errors import AgoInputError
    from ago_runtime.shards import parse_shard, shard_indices

    for n in (1, 3, 7, 41, 50):
        parts = [shard_indices(range(41), (k, n)) for k in range(1, n + 1)]
        assert sum(parts, []) == list(range(41))
        assert max(map(len, parts)) - min(map(len, parts)) <= 1
    assert parse_shard("2/8") == (2, 8) and parse_shard(None) is None
    for bad in ("0/4", "5/4", "1", "a/b", "1/0"):
        with pytest.raises(AgoInputError, match="--shard"):
            parse_shard(bad)


def test_export_parity_frame_takes_a_dataroot():
    from ago_export.export import parity_frame
    from ago_runtime.errors import AgoInputError
    from ago_runtime.geometry.camera import Rig

    root = scene_root()
    images, rig, name = parity_frame(root, True, Rig.nuscenes_like(1600, 900))
    assert len(images) == 6 and "sample" in name
    with pytest.raises(AgoInputError, match="--parity-frame"):
        parity_frame(root / "nowhere", True, Rig.nuscenes_like(1600, 900))
    with pytest.raises(AgoInputError, match="pass the dataroot itself"):
        parity_frame(root / "v1.0-mini", True, Rig.nuscenes_like(1600, 900))


def test_eval_without_gt_names_the_lidar_metric():
    from ago_runtime.errors import AgoInputError
    from ago_runtime.formats.nuscenes import NuScenesDataset
    from ago_train.evaluate import check_has_gt

    ds = NuScenesDataset(scene_root(), load_images=False, load_extras=False)
    with pytest.raises(AgoInputError, match="ago metric --pred P --lidar"):
        check_has_gt(ds, ds.split("val"), scene_root())


@pytest.fixture(scope="module")
def trimmed_root(tmp_path_factory):
    """The shared scene without its box tables (links, not copies)."""
    root = scene_root()
    out = tmp_path_factory.mktemp("trimmed") / "nuscenes"
    (out / "v1.0-mini").mkdir(parents=True)
    (out / "samples").symlink_to(root / "samples")
    for table in (root / "v1.0-mini").iterdir():
        if table.stem not in ("sample_annotation", "instance", "category"):
            (out / "v1.0-mini" / table.name).symlink_to(table)
    return out


@pytest.mark.parametrize("args, needles", [
    (["infer", "--images", "{root}/v1.0-mini", "--out", "o"], ["pass the dataroot itself", "nuscenes-scene"]),
    (["infer", "--images", "{root}/samples", "--out", "o"], ["pass the dataroot itself"]),
    (["pseudo-labels", "--data", "{root}", "--out", "o"], ["--segmenter boxes"]),
    (["pseudo-labels", "--data", "{root}", "--out", "o", "--segmenter", "boxes", "--shard", "5/4"], ["--shard"]),
    (["infer", "--images", "{root}", "--out", "o", "--shard", "0/3"], ["--shard"]),
    (["pseudo-labels", "--data", "{trimmed}", "--out", "o", "--segmenter", "boxes"], ["sample_annotation.json",
                                                                                      "--segmenter files"]),
    (["pseudo-labels", "--data", "{root}", "--out", "o", "--segmenter", "boxes", "--split", "test"],
     ["splits.json", "'all'"]),
])
def test_real_dataroot_refusals(tmp_path, trimmed_root, args, needles):
    root = scene_root()
    args = [a.format(root=root, trimmed=trimmed_root) for a in args]
    r = run_ago(args, tmp_path)
    assert_one_error_line(r, *needles)
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_infer_shard_on_the_real_scene(tmp_path):
    root = scene_root()
    r = run_ago(["infer", "--images", root, "--shard", "41/41", "--picture", "none", "--out", "o"], tmp_path)
    assert r.code == 0, r.stderr
    from ago_runtime.formats.nuscenes import NuScenesDataset

    last = NuScenesDataset(root, load_images=False, load_extras=False).sample_tokens[-1]
    assert [p.name for p in (tmp_path / "o").glob("*.npz")] == [f"{last}.npz"]
    assert "note: using shard 41/41: 1 frames" in r.stdout


def test_show_and_retrieve_take_the_dataroot(tmp_path):
    root = scene_root()
    r = run_ago(["show", root, "--index", "0", "--out", "rig.png"], tmp_path)
    assert r.code == 0, r.stderr
    r = run_ago(["retrieve", "--images", root, "--phrase", "bus", "--out", "r"], tmp_path)
    assert r.code == 0, r.stderr
    assert "note: using keyframe" in r.stdout and len(list((tmp_path / "r").glob("*_bus.npz"))) == 1
