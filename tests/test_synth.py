"""Tests of `ago synth` (ago_train/synth): determinism, class coverage, sensor/GT consistency, CLI.

A tiny world (2 scenes x 3 keyframes, 160x90 images, 50x50x4 grid) is generated once in memory.
"""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from ago_runtime.classes import FREE, NUM_SEMANTIC
from ago_runtime.errors import AgoInputError
from ago_train.synth.config import SynthConfig
from ago_train.synth.generate import generate_scene

TINY = dict(seed=0, num_scenes=2, frames_per_scene=3, image_width=160, image_height=90, grid_shape=(50, 50, 4))


@pytest.fixture(scope="module")
def tiny_config() -> SynthConfig:
    return SynthConfig(**TINY)


@pytest.fixture(scope="module")
def tiny_frames(tiny_config) -> list[dict]:
    return [fr for s in range(tiny_config.num_scenes) for fr in generate_scene(tiny_config, s)]


def _lidar_in_ego(frame) -> np.ndarray:
    m = frame["lidar2ego"]
    return frame["lidar_points"][:, :3].astype(np.float64) @ m[:3, :3].T + m[:3, 3]


def test_frame_contents(tiny_frames, tiny_config):
    grid = tiny_config.grid()
    for fr in tiny_frames:
        assert set(fr["images"]) == {c.name for c in fr["rig"]}
        for cam in fr["rig"]:
            assert fr["images"][cam.name].shape == (90, 160, 3) and fr["images"][cam.name].dtype == np.uint8
            assert fr["extras"]["semantic"][cam.name].shape == (90, 160)
            assert fr["extras"]["depth"][cam.name].dtype == np.float32
        pts = fr["lidar_points"]
        assert pts.dtype == np.float32 and pts.shape[1] == 5 and len(pts) > 10000
        assert pts[:, 4].min() >= 0 and pts[:, 4].max() <= tiny_config.lidar_beams - 1
        assert 0 <= pts[:, 3].min() and pts[:, 3].max() <= 255
        assert np.linalg.norm(pts[:, :3], axis=1).max() <= tiny_config.lidar_max_range + 0.2
        assert fr["gt"].shape == grid.shape
    ts = [fr["timestamp_us"] for fr in tiny_frames[:3]]
    assert np.diff(ts).tolist() == [500_000, 500_000]  # 2 Hz keyframes


def test_deterministic(tiny_frames, tiny_config):
    again = list(itertools.islice(generate_scene(tiny_config, 0), 2))
    for a, b in zip(tiny_frames[:2], again):
        for cam in a["images"]:
            np.testing.assert_array_equal(a["images"][cam], b["images"][cam])
        np.testing.assert_array_equal(a["lidar_points"], b["lidar_points"])
        np.testing.assert_array_equal(a["gt"].semantics, b["gt"].semantics)
        np.testing.assert_array_equal(a["gt"].mask_camera, b["gt"].mask_camera)
        assert [x.instance for x in a["annotations"]] == [x.instance for x in b["annotations"]]
    other = next(generate_scene(SynthConfig(**{**TINY, "seed": 1}), 0))
    assert not np.array_equal(other["images"]["CAM_FRONT"], tiny_frames[0]["images"]["CAM_FRONT"])


def test_all_classes_present(tiny_frames):
    counts = sum(np.bincount(fr["gt"].semantics.ravel(), minlength=FREE + 1) for fr in tiny_frames)
    missing = [c for c in range(NUM_SEMANTIC + 1) if counts[c] == 0]
    assert not missing, f"classes never in GT: {missing}"
    # the big surfaces dominate, as in Occ3D
    share = counts[:NUM_SEMANTIC] / counts[:NUM_SEMANTIC].sum()
    assert share[[11, 13, 14, 15, 16]].sum() > 0.6
    assert share[4] > share[2]  # cars more common than bicycles


def test_lidar_agrees_with_camera_depth(tiny_frames):
    for fr in tiny_frames[:3]:
        p = _lidar_in_ego(fr)
        agree = []
        for cam in fr["rig"]:
            uv, d, ok = cam.project(p)
            dm = fr["extras"]["depth"][cam.name][np.floor(uv[ok, 1]).astype(int), np.floor(uv[ok, 0]).astype(int)]
            seen = dm > 0
            agree.append(np.abs(d[ok][seen] - dm[seen]) <= np.maximum(0.3, 0.05 * dm[seen]))
        agree = np.concatenate(agree)
        assert len(agree) > 5000
        assert agree.mean() > 0.85, agree.mean()


def test_gt_consistent_with_lidar_and_cameras(tiny_frames, tiny_config):
    grid = tiny_config.grid()
    for fr in tiny_frames[:3]:
        gt = fr["gt"]
        idx, inside = grid.points_to_index(_lidar_in_ego(fr))
        i, j, k = idx[inside].T
        assert (gt.semantics[i, j, k] != FREE).mean() > 0.85          # returns land in occupied voxels
        assert gt.mask_lidar[i, j, k].mean() > 0.99                   # and in observed ones
        assert (gt.semantics[i, j, k] == fr["lidar_classes"][inside]).mean() > 0.6
        assert 0.02 < gt.mask_lidar.mean() < 0.9
        # camera mask: every visible voxel lies in some camera's view (its centre or its top-face centre,
        # the two probes of the visibility test); occluded ones exist
        centres = grid.centres().reshape(-1, 3)
        tops = centres + np.float32([0, 0, 0.49 * grid.voxel_size[2]])
        in_view = np.zeros(len(centres), bool)
        for cam in fr["rig"]:
            in_view |= cam.project(centres)[2] | cam.project(tops)[2]
        cam_mask = gt.mask_camera.ravel().astype(bool)
        assert cam_mask.any() and not (cam_mask & ~in_view).any()
        assert cam_mask.sum() < 0.95 * in_view.sum()
        # voxels of LiDAR returns seen by a camera are mostly camera-visible too
        flat = grid.flat_index(idx[inside])
        seen = in_view[flat]
        assert cam_mask[flat[seen]].mean() > 0.7


def test_images_are_textured_not_colour_codes(tiny_frames):
    for fr in tiny_frames[:2]:
        for cls in (11, 15, 16):
            pix = np.concatenate([fr["images"][c][fr["extras"]["semantic"][c] == cls] for c in fr["images"]])
            assert len(pix) > 200
            assert pix.astype(float).std(axis=0).mean() > 6.0, cls
    # cars differ from each other: per-instance colours
    car_means = []
    for fr in tiny_frames:
        for c in fr["images"]:
            m = fr["extras"]["semantic"][c] == 4
            if m.sum() > 30:
                car_means.append(fr["images"][c][m].mean(axis=0))
    assert len(car_means) >= 2 and np.ptp(np.array(car_means), axis=0).max() > 20


def test_annotations(tiny_frames):
    frames = tiny_frames[:3]
    for fr in frames:
        assert fr["annotations"]
        for box in fr["annotations"]:
            assert box.category.split(".")[0] in ("vehicle", "human", "movable_object", "static_object")
            assert box.size.shape == (3,) and np.all(box.size > 0)
    cats = {b.category for fr in tiny_frames for b in fr["annotations"]}
    assert {"vehicle.car", "human.pedestrian.adult", "movable_object.trafficcone", "movable_object.barrier"} <= cats
    # a moving object keeps its instance id and moves by velocity * 0.5 s
    first = {b.instance: b for b in frames[0]["annotations"]}
    moved = 0
    for b in frames[1]["annotations"]:
        a = first.get(b.instance)
        if a is not None and np.linalg.norm(a.velocity) > 0.5:
            np.testing.assert_allclose(b.center[:2], a.center[:2] + 0.5 * a.velocity, atol=1e-6)
            moved += 1
    assert moved > 0


def test_config_validation():
    with pytest.raises(AgoInputError):
        SynthConfig(num_scenes=0)
    with pytest.raises(AgoInputError):
        SynthConfig(grid_shape=(10, 10))
    assert SynthConfig(grid_shape=(100, 100, 8)).grid().voxel_size == (0.8, 0.8, 0.8)
    assert SynthConfig(num_scenes=10).val_scene_indices() == [8, 9]


def test_cli_writes_nuscenes_layout(tmp_path):
    from typer.testing import CliRunner

    from ago_runtime.cli import app

    out = tmp_path / "synth"
    result = CliRunner().invoke(app, ["synth", "--out", str(out), "--scenes", "2", "--frames", "2",
                                      "--image-size", "96x54", "--grid", "25x25x4"])
    assert result.exit_code == 0, result.output
    splits = json.loads((out / "splits.json").read_text())
    assert splits == {"train": ["synth-0000-0000"], "val": ["synth-0000-0001"]}
    assert len(list((out / "samples" / "CAM_FRONT").glob("*.jpg"))) == 4
    assert len(list((out / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))) == 4
    assert len(list((out / "gts").glob("*/*/labels.npz"))) == 4
    assert len(list((out / "synthetic" / "depth" / "CAM_BACK").glob("*.png"))) == 4
    assert (out / "v1.0-trainval" / "sample_annotation.json").is_file()
    from ago_runtime.formats.nuscenes import NuScenesDataset

    ds = NuScenesDataset(out)
    frame = ds[0]
    assert len(ds) == 4 and frame.gt.shape == (25, 25, 4) and frame.images["CAM_FRONT"].shape == (54, 96, 3)
    bad = CliRunner().invoke(app, ["synth", "--out", str(out), "--image-size", "big"])
    assert isinstance(bad.exception, AgoInputError)


def test_parallel_scenes_write_the_same_dataset(tmp_path):
    """`ago synth --jobs 2` renders scenes in worker processes; the files are byte-for-byte those of --jobs 1."""
    import filecmp

    from ago_train.synth.config import SynthConfig
    from ago_train.synth.generate import write_dataset

    cfg = SynthConfig(seed=4, num_scenes=2, frames_per_scene=2, image_width=64, image_height=36,
                      grid_shape=(20, 20, 4), val_fraction=0.5)
    write_dataset(cfg, tmp_path / "one", progress=False, jobs=1)
    write_dataset(cfg, tmp_path / "two", progress=False, jobs=2)
    files = sorted(p.relative_to(tmp_path / "one") for p in (tmp_path / "one").rglob("*") if p.is_file())
    assert files and files == sorted(p.relative_to(tmp_path / "two") for p in (tmp_path / "two").rglob("*")
                                     if p.is_file())
    _, mismatch, errors = filecmp.cmpfiles(tmp_path / "one", tmp_path / "two", [str(f) for f in files], shallow=False)
    assert not mismatch and not errors


def test_barriers_stand_by_the_ego_road_not_only_around_construction_sites():
    """Road-edge barriers (road works and a closed-off row of 4-6) near the ego route in every scene: a
    town whose barriers are all construction-site fences teaches a model nothing about nuScenes-like
    lane-side barriers (issue "The model must see": barrier IoU on fresh towns)."""
    from ago_train.synth.world import build_world

    for seed, scene in ((0, 1), (7, 0)):
        w = build_world(SynthConfig(seed=seed), scene)
        ego_road = min((r for r in w.roads if r.axis == 0), key=lambda r: abs(r.pos))   # the ego drives y = 0
        barriers = np.array([w.obj_pos0[i] for i, c in enumerate(w.obj_category) if c == "movable_object.barrier"])
        hw = ego_road.half_width
        on_road = barriers[np.abs(barriers[:, 1]) < hw]
        assert len(on_road) >= 6, (seed, scene, len(on_road))
        # the row: at least 4 barriers 2.2 m apart along one road edge
        ys = np.round(on_road[:, 1], 2)
        assert max(np.sum(ys == y) for y in np.unique(ys)) >= 4
