"""Issue 38: the Occ3D-Waymo layout `ago synth --rig waymo` writes, with its LiDAR (KITTI-format velodyne
.bin, vehicle frame) and per-pixel extras (Occ3D-Waymo ids), read back by `Occ3DWaymoDataset` through
`open_dataset`, with the interface every consumer of `NuScenesDataset` uses, and its bad inputs refused."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from ago_runtime.classes import OCC3D_WAYMO
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.datasets import check_label_table, dataset_layout, open_dataset
from ago_runtime.formats.occ3d_waymo import Occ3DWaymoLabels, gt_path
from ago_runtime.formats.occ3d_waymo_dataset import Occ3DWaymoDataset
from ago_runtime.formats.occ3d_waymo_writer import VELODYNE_COLUMNS
from ago_runtime.geometry.grid import Grid
from ago_runtime.vocab.prompts import parse_prompt_file
from ago_train.synth.config import SynthConfig
from ago_train.synth.generate import generate_scene, write_dataset
from ago_train.synth.rigs import WAYMO_CAMERAS
from ago_train.synth.waymo_labels import NUSCENES_TO_WAYMO

TINY = dict(seed=3, num_scenes=2, frames_per_scene=3, image_width=96, image_height=64, grid_shape=(40, 40, 4),
            val_fraction=0.5, rig_name="waymo")
FREE = OCC3D_WAYMO.free_id


@pytest.fixture(scope="module")
def waymo_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("waymo") / "w"
    write_dataset(SynthConfig(**TINY), root, progress=False)
    return root


@pytest.fixture(scope="module")
def rendered():
    """The frames of scene 0 in memory (what the writer was given), and the same scene with the nuScenes rig."""
    return list(generate_scene(SynthConfig(**TINY), 0))


def _voxel_labels(sem: np.ndarray, points: np.ndarray) -> np.ndarray:
    idx, ok = Grid.with_shape(sem.shape).points_to_index(points)
    return sem[tuple(idx[ok].T)]


def test_velodyne_files_are_kitti_format_float32_six_columns_in_the_ego_frame(waymo_root, rendered):
    fr = rendered[1]
    path = waymo_root / "kitti_format" / "training" / "velodyne" / "0000001.bin"
    raw = np.fromfile(path, np.float32)
    assert len(VELODYNE_COLUMNS) == 6 and raw.size % 6 == 0
    rows = raw.reshape(-1, 6)
    assert len(rows) == len(fr["lidar_points"])
    m = fr["lidar2ego"]
    assert not np.allclose(m[:3, 3], 0)                       # the synthetic LiDAR is not at the ego origin ...
    expect = fr["lidar_points"][:, :3].astype(np.float64) @ m[:3, :3].T + m[:3, 3]
    np.testing.assert_allclose(rows[:, :3], expect, atol=1e-4)  # ... and the file holds ego-frame points
    np.testing.assert_array_equal(rows[:, 3], fr["lidar_points"][:, 3])   # intensity
    assert np.all(rows[:, 4] == 0) and np.all(rows[:, 5] == np.float32(fr["timestamp_us"]))
    # the points lie on the ground truth's occupied voxels (the same ego frame as the grid)
    on = _voxel_labels(fr["gt"].semantics, rows[:, :3].astype(np.float64))
    assert (on != FREE).mean() > 0.8


def test_synthetic_maps_hold_occ3d_waymo_ids_that_agree_with_the_ground_truth(waymo_root, rendered):
    ds = open_dataset(waymo_root)
    frame = ds[ds.index_of("0000002")]
    fr = rendered[2]
    seen = set()
    nuscenes = list(generate_scene(SynthConfig(**{**TINY, "rig_name": "waymo", "layout": "nuscenes"}), 0))[2]
    for cam in frame.rig:
        sem = frame.extras["semantic"][cam.name]
        np.testing.assert_array_equal(sem, fr["extras"]["semantic"][cam.name])
        assert set(np.unique(sem).tolist()) <= set(OCC3D_WAYMO.ids) | {255}
        ns = nuscenes["extras"]["semantic"][cam.name]                  # the same pixels in nuScenes ids
        assert np.array_equal(sem == 255, ns == 255)
        differs = (NUSCENES_TO_WAYMO[ns] != sem) & (ns != 255)
        seen |= set(sem[differs].tolist())
        # a pixel's label is the label of the voxel its depth lands in (where that voxel is occupied)
        depth = frame.extras["depth"][cam.name]
        v, u = np.nonzero((depth > 0) & (sem != 255))
        rays = np.linalg.inv(cam.intrinsics) @ np.stack([u + 0.5, v + 0.5, np.ones_like(u)]).astype(float)
        pts = (rays * depth[v, u]).T @ cam.cam2ego[:3, :3].T + cam.cam2ego[:3, 3]
        idx, ok = Grid.with_shape(frame.gt.shape).points_to_index(pts)
        vox = frame.gt.semantics[tuple(idx[ok].T)]
        occupied = vox != FREE
        assert (vox[occupied] == sem[v, u][ok][occupied]).mean() > 0.7, cam.name
    # the material refinements (poles, tree trunks, signs ...) reach the pixels, as they reach the voxels
    assert seen & {OCC3D_WAYMO.id_of(n) for n in ("pole", "tree_trunk", "sign", "traffic_light", "bicyclist")}


def test_dataset_gives_frames_with_the_consumers_interface(waymo_root, rendered):
    assert dataset_layout(waymo_root) == "occ3d-waymo"
    ds = open_dataset(waymo_root, load_images=True)
    assert isinstance(ds, Occ3DWaymoDataset) and ds.class_table is OCC3D_WAYMO
    assert ds.sample_tokens == ["0000000", "0000001", "0000002", "1000000", "1000001", "1000002"]
    assert ds.scenes() == ["training/000", "validation/000"] and ds.scene_of(4) == "validation/000"
    assert ds.split("train") == [0, 1, 2] and ds.split("val") == [3, 4, 5] and ds.split("all") == list(range(6))
    assert ds.split_note("train") is None
    assert ds.indices_of(["validation/000", "0000001"]) == [3, 4, 5, 1]
    assert ds.neighbours(1, 2, 1) == [2, 0] and ds.neighbours(3, 5, 1) == [4, 5]
    assert ds.nonkey_sweeps(0) == [] and ds.num_nonkey_lidar == 0 and ds.has_lidar()
    with pytest.raises(AgoInputError, match="nope"):
        ds.indices_of(["nope"])

    f = ds[1]
    fr = rendered[1]
    assert (f.token, f.scene, f.timestamp) == ("0000001", "training/000", fr["timestamp_us"])
    assert f.rig.names == list(WAYMO_CAMERAS)
    assert [(c.width, c.height) for c in f.rig] == [(c.width, c.height) for c in fr["rig"]]
    assert len({c.height for c in f.rig}) == 2                        # two image heights, as Waymo
    for c, c0 in zip(f.rig, fr["rig"]):
        np.testing.assert_allclose(c.intrinsics, c0.intrinsics, atol=1e-5)
        np.testing.assert_allclose(c.cam2ego, c0.cam2ego, atol=1e-8)
        assert f.images[c.name].shape == (c.height, c.width, 3)
        assert np.abs(f.images[c.name].astype(int) - fr["images"][c.name]).mean() < 6   # JPEG
    np.testing.assert_allclose(f.ego2global, fr["ego2global"], atol=1e-8)
    assert f.lidar.points.shape == (len(fr["lidar_points"]), 5) and np.array_equal(f.lidar.lidar2ego, np.eye(4))
    # the LiDAR in this frame's ego frame = the synth's LiDAR-frame points moved by its lidar2ego
    m = fr["lidar2ego"]
    np.testing.assert_allclose(f.lidar.points_in(f.ego2global),
                               fr["lidar_points"][:, :3] @ m[:3, :3].T + m[:3, 3], atol=1e-3)
    # GT: Waymo ids (free 23) kept; mask_camera = final_voxel_state & infov; mask_lidar = origin_voxel_state
    w = fr["gt"]
    assert np.array_equal(f.gt.semantics, w.semantics) and FREE in np.unique(f.gt.semantics)
    assert np.array_equal(f.gt.mask_camera, w.mask_camera & w.mask_fov)
    assert np.array_equal(f.gt.mask_lidar, w.mask_lidar)
    # without splits.json: the training/ and validation/ folders
    bare = waymo_root.parent / "bare"
    shutil.copytree(waymo_root, bare)
    (bare / "splits.json").unlink()
    b = open_dataset(bare, load_images=False, load_extras=False)
    assert b.split("train") == [0, 1, 2] and "training/" in b.split_note("train")
    assert b[0].images == {} and b[0].extras == {} and b[0].rig.names == list(WAYMO_CAMERAS)


def test_label_tables_must_agree(waymo_root):
    ds = open_dataset(waymo_root, load_images=False)
    check_label_table(ds, parse_prompt_file("waymo/cw_waymo"))
    check_label_table(ds, parse_prompt_file("waymo/ow_waymo"))
    with pytest.raises(AgoInputError, match="occ3d_waymo"):
        check_label_table(ds, parse_prompt_file("cw"))


def _copy(root: Path, tmp_path: Path) -> Path:
    out = tmp_path / "copy"
    shutil.copytree(root, out)
    return out


@pytest.mark.parametrize("damage, needle", [
    (lambda i: i["frames"].update({"0000009": i["frames"]["0000001"]}), "does not match"),
    (lambda i: i["frames"].update({"../0000001": {}}), "seven digits"),
    (lambda i: i["frames"]["0000001"]["cameras"].pop("SIDE_LEFT"), "SIDE_LEFT"),
    (lambda i: i.update(cameras=["FRONT", "FRONT"]), "distinct"),
    (lambda i: i["frames"]["0000001"].update(ego2global=[[1, 0], [0, 1]]), "ego2global"),
    (lambda i: i.update(frames=[]), "frames"),
])
def test_bad_cam_infos_is_one_error_naming_the_file(waymo_root, tmp_path, damage, needle):
    root = _copy(waymo_root, tmp_path)
    infos = json.loads((root / "cam_infos.json").read_text())
    damage(infos)
    (root / "cam_infos.json").write_text(json.dumps(infos))
    with pytest.raises(AgoInputError) as e:
        open_dataset(root)
    assert "cam_infos.json" in str(e.value) and needle in str(e.value)


def test_bad_files_are_refused_naming_them(waymo_root, tmp_path):
    root = _copy(waymo_root, tmp_path)
    (root / "kitti_format" / "training" / "image_3" / "0000001.jpg").unlink()
    lidar = root / "kitti_format" / "training" / "velodyne" / "0000002.bin"
    lidar.write_bytes(lidar.read_bytes()[:-4])
    gt = gt_path(root, "training", 0, 0)
    Occ3DWaymoLabels(*(np.zeros((4, 4, 4), np.uint8) for _ in range(4))).save(gt)    # another grid
    ds = open_dataset(root, grid=Grid.with_shape((40, 40, 4)))
    with pytest.raises(AgoInputError, match="image_3/0000001.jpg"):
        ds[1]
    with pytest.raises(AgoInputError, match="not a multiple of 24"):
        ds[2]
    with pytest.raises(AgoInputError, match="000_04.npz.*grid"):
        ds[0]
    with pytest.raises(AgoInputError, match="not a dataset root"):
        open_dataset(root / "kitti_format")


def test_nuscenes_layout_still_opens_as_nuscenes(tmp_path):
    from ago_runtime.formats.nuscenes import NuScenesDataset

    root = tmp_path / "n"
    write_dataset(SynthConfig(seed=1, num_scenes=1, frames_per_scene=1, image_width=64, image_height=36,
                              grid_shape=(20, 20, 4)), root, progress=False)
    ds = open_dataset(root)
    assert dataset_layout(root) == "nuscenes" and isinstance(ds, NuScenesDataset)
    assert ds.class_table.name == "occ3d_nuscenes" and ds.gt_file(0).name == "labels.npz"
    with pytest.raises(AgoInputError, match="occ3d_nuscenes"):
        check_label_table(ds, parse_prompt_file("waymo/ow_waymo"))


def test_frame_mask_camera_is_final_voxel_state_and_infov(waymo_root, tmp_path):
    """As Occ3D-Waymo's loaders use_camera_mask and use_infov_mask: a voxel seen by the camera pass but
    outside the five cameras' field of view is not scored; the Waymo ids, free 23 included, are kept."""
    root = _copy(waymo_root, tmp_path)
    rng = np.random.default_rng(0)
    sem = rng.choice(np.array(list(OCC3D_WAYMO.ids) + [FREE], np.uint8), size=(40, 40, 4))
    final, infov, lidar = (rng.integers(0, 2, (40, 40, 4)).astype(np.uint8) for _ in range(3))
    Occ3DWaymoLabels(sem, lidar, final, infov).save(gt_path(root, "validation", 0, 1))
    gt = open_dataset(root, load_images=False)[4].gt
    assert np.array_equal(gt.semantics, sem)
    assert np.array_equal(gt.mask_camera, final & infov) and not np.array_equal(gt.mask_camera, final)
    assert np.array_equal(gt.mask_lidar, lidar)


def test_front_camera_rig_in_the_waymo_layout(tmp_path):
    """`ago synth --rig front` (N = 1) writes the same layout with one camera; the reader gives one-camera frames."""
    root = tmp_path / "f"
    write_dataset(SynthConfig(**{**TINY, "rig_name": "front", "num_scenes": 1, "frames_per_scene": 2}), root,
                  progress=False)
    ds = open_dataset(root)
    f = ds[1]
    assert ds.camera_names == ["FRONT"] and f.rig.names == ["FRONT"] and list(f.images) == ["FRONT"]
    assert sorted(f.extras["semantic"]) == ["FRONT"] and len(f.lidar.points) > 0 and f.gt.shape == (40, 40, 4)
    # the camera mask lies in the one camera's field of view (infov): nothing behind the car is scored
    xs = Grid.with_shape(f.gt.shape).axis_centres()[0]
    assert f.gt.mask_camera.any() and not f.gt.mask_camera[xs < -1].any()
