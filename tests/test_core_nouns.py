"""Tests of the shared nouns: Grid, Camera/Rig, Occ3DLabels, atomic writes, Preprocess, CLI errors."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest

from ago_runtime.atomic import atomic_path, save_npz, write_json
from ago_runtime.geometry.camera import CAMERA_NAMES, Camera, Rig
from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.grid import Grid
from ago_runtime.formats.occ3d import Occ3DLabels
from ago_runtime.geometry.preprocess import Preprocess


def test_occ3d_grid_matches_the_dataset_definition():
    g = Grid.occ3d()
    assert g.shape == (200, 200, 16)
    xs, ys, zs = g.axis_centres()
    assert xs[0] == pytest.approx(-39.8) and xs[5] == pytest.approx(-40 + 0.4 * 5 + 0.2)
    assert zs[0] == pytest.approx(-0.8) and zs[-1] == pytest.approx(5.2)
    idx, inside = g.points_to_index(np.array([[-39.9, -39.9, -0.9], [0.1, 0.1, 0.1], [40.1, 0, 0]]))
    assert idx[0].tolist() == [0, 0, 0] and idx[1].tolist() == [100, 100, 2]
    assert inside.tolist() == [True, True, False]
    assert g.flat_index(np.array([[1, 2, 3]]))[0] == (1 * 200 + 2) * 16 + 3
    assert Grid.from_dict(g.to_dict()) == g


def test_coarse_grid_keeps_the_range():
    g = Grid.with_shape((100, 100, 8))
    assert g.shape == (100, 100, 8) and g.voxel_size == pytest.approx((0.8, 0.8, 0.8))
    assert g.centres()[0, 0, 0].tolist() == pytest.approx([-39.6, -39.6, -0.6])


def test_camera_projection_round_trip_and_scaling():
    rig = Rig.nuscenes_like(1600, 900)
    front = rig["CAM_FRONT"]
    uv, depth, ok = front.project(np.array([[20.0, 0.0, 1.5], [-20.0, 0.0, 1.5]]))
    assert ok.tolist() == [True, False]
    assert abs(uv[0, 0] - 800) < 20 and depth[0] == pytest.approx(20.0 - 1.70)
    # ego2img agrees with project()
    h = front.ego2img @ np.array([20.0, 0.0, 1.5, 1.0])
    assert h[:2] / h[2] == pytest.approx(uv[0])
    small = front.scaled(400, 225)
    uv2, _, _ = small.project(np.array([[20.0, 3.0, 0.5]]))
    uv1, _, _ = front.project(np.array([[20.0, 3.0, 0.5]]))
    assert uv2[0] == pytest.approx(uv1[0] / 4)
    # every camera sees the point straight along its own axis
    for cam in rig:
        d = cam.cam2ego[:3, 2]
        p = cam.cam2ego[:3, 3] + 10 * d
        _, _, ok = cam.project(p[None])
        assert ok[0], cam.name


def test_rig_of_any_cameras_refuses_what_does_not_fit_and_bad_calibration():
    rig = Rig.nuscenes_like(160, 90)
    five = Rig([c for c in rig if c.name != "CAM_BACK"])           # any 1..12 distinct cameras make a rig
    assert five.names == [c for c in CAMERA_NAMES if c != "CAM_BACK"]
    with pytest.raises(AgoInputError, match="camera CAM_BACK: the model's rig takes it"):
        five.ordered_as(CAMERA_NAMES, "calib.json")                 # ... but not the rig a bundle was trained for
    with pytest.raises(AgoInputError, match="camera CAM_BACK: not a camera of the model's rig"):
        rig.ordered_as(five.names)
    assert rig.ordered_as(list(reversed(CAMERA_NAMES))).names == list(reversed(CAMERA_NAMES))
    with pytest.raises(AgoInputError, match="CAM_FRONT: named more than once"):
        Rig([rig["CAM_FRONT"], rig["CAM_FRONT"]])
    with pytest.raises(AgoInputError, match="1..12 cameras"):
        Rig([])
    with pytest.raises(AgoInputError, match="1..12 cameras"):
        Rig([Camera(f"C{i}", rig["CAM_FRONT"].intrinsics, np.eye(4), 160, 90) for i in range(13)])
    with pytest.raises(AgoInputError, match="letters, digits"):
        Rig([Camera("../x", rig["CAM_FRONT"].intrinsics, np.eye(4), 160, 90)])
    bad = Camera("CAM_FRONT", np.full((3, 3), np.nan), np.eye(4), 10, 10)
    with pytest.raises(AgoInputError, match="NaN"):
        bad.validate("calib.json")
    singular = Camera("CAM_FRONT", np.zeros((3, 3)), np.eye(4), 10, 10)
    with pytest.raises(AgoInputError, match="singular"):
        singular.validate("calib.json")
    assert Rig.from_dict(rig.to_dict()).ego2img() == pytest.approx(rig.ego2img())


def test_occ3d_labels_round_trip_and_shape_check(tmp_path):
    rng = np.random.default_rng(0)
    lab = Occ3DLabels(rng.integers(0, 18, (4, 5, 2), dtype=np.uint8), np.ones((4, 5, 2), np.uint8),
                      np.zeros((4, 5, 2), np.uint8))
    p = tmp_path / "a" / "labels.npz"
    lab.save(p)
    back = Occ3DLabels.load(p, shape=(4, 5, 2))
    assert np.array_equal(back.semantics, lab.semantics)
    with pytest.raises(AgoInputError, match="does not match the grid"):
        Occ3DLabels.load(p, shape=(200, 200, 16))
    p.write_bytes(p.read_bytes()[:50])
    with pytest.raises(AgoInputError, match="labels.npz"):
        Occ3DLabels.load(p)


def test_real_occ3d_frame_loads(occ3d_sample_labels):
    lab = Occ3DLabels.load(occ3d_sample_labels, shape=Grid.occ3d().shape)
    assert lab.semantics.max() == 17 and lab.mask_camera.max() == 1


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.json"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert not target.exists() and list(tmp_path.iterdir()) == []
    write_json(target, {"a": 1})
    assert target.read_text().strip().startswith("{")
    with pytest.raises(TypeError):
        save_npz(tmp_path / "x.npz", a=np.array([object()], dtype=object))
    # a chosen deflate level (what `ago infer` writes) reads back with np.load, without pickles
    sem = np.random.default_rng(0).integers(0, 18, (20, 20, 4), dtype=np.uint8)
    save_npz(tmp_path / "fast.npz", compresslevel=1, semantics=sem, class_names=np.array(["car", "free"]),
             free_index=np.array(1, np.int64))
    with np.load(tmp_path / "fast.npz", allow_pickle=False) as z:
        assert np.array_equal(z["semantics"], sem) and list(z["class_names"]) == ["car", "free"]
        assert int(z["free_index"]) == 1
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_preprocess_shapes_normalisation_and_missing_camera():
    pre = Preprocess(64, 32)
    rig = Rig.nuscenes_like(160, 90)
    imgs = {c: np.full((90, 160, 3), 128, np.uint8) for c in CAMERA_NAMES}
    x = pre.images(imgs, rig)
    assert x.shape == (6, 3, 32, 64) and x.dtype == np.float32
    assert x[0, 0, 0, 0] == pytest.approx((128 / 255 - 0.485) / 0.229, rel=1e-5)
    # bit-equal to resizing, normalising (H, W, 3) and transposing, on varied pixels and per channel
    rng = np.random.default_rng(1)
    varied = {c: rng.integers(0, 256, (90, 160, 3), dtype=np.uint8) for c in CAMERA_NAMES}
    mean = np.asarray(pre.mean, np.float32) * 255.0
    inv_std = 1.0 / (np.asarray(pre.std, np.float32) * 255.0)
    want = np.stack([((cv2.resize(varied[c], (64, 32), interpolation=cv2.INTER_AREA).astype(np.float32) - mean)
                      * inv_std).transpose(2, 0, 1) for c in CAMERA_NAMES])
    assert np.array_equal(pre.images(varied, rig), want)
    del imgs["CAM_BACK"]
    with pytest.raises(AgoInputError, match="CAM_BACK"):
        pre.images(imgs, rig, source="dir/")
    e = pre.ego2img(Rig.nuscenes_like(160, 90))
    assert e.shape == (6, 4, 4) and e.dtype == np.float32


def test_preprocess_pads_the_shorter_cameras_of_a_rig():
    """A rig of two image sizes (Occ3D-Waymo's side cameras are shorter): the largest fills the canvas, the
    others are scaled by the same factors, top-left, padded with 0; ego2img follows the same scaling."""
    from ago_runtime.geometry.camera import level_camera

    front = level_camera("FRONT", 1.5, 0, 2, 0.0, np.deg2rad(50), 192, 128)
    side = level_camera("SIDE_LEFT", 1.2, 0.1, 2, np.pi / 2, np.deg2rad(50), 192, 88)
    rig = Rig([front, side])
    pre = Preprocess(96, 64)
    assert pre.camera_sizes(rig) == [(96, 64), (96, 44)]
    imgs = {"FRONT": np.full((128, 192, 3), 200, np.uint8), "SIDE_LEFT": np.full((88, 192, 3), 200, np.uint8)}
    x = pre.images(imgs, rig)
    assert x.shape == (2, 3, 64, 96)
    v = (200 / 255 - 0.485) / 0.229
    assert x[0, 0].min() == pytest.approx(v, rel=1e-5)                  # the front camera fills its canvas
    assert x[1, 0, :44].min() == pytest.approx(v, rel=1e-5) and np.all(x[1, :, 44:] == 0)   # the side: padded below
    m = pre.ego2img(rig)
    p = side.cam2ego @ np.array([0.5, 0.2, 8.0, 1.0])   # a point 8 m in front of SIDE_LEFT
    uv_native, _, ok = side.project(p[None, :3])
    h = m[1] @ p
    assert ok[0] and h[:2] / h[2] == pytest.approx(uv_native[0] * 0.5, rel=1e-5)   # same scale on both axes
    # a rig of one image size fills every canvas, as before (nuScenes)
    assert pre.camera_sizes(Rig.nuscenes_like(160, 90)) == [(96, 64)] * 6


def test_cli_help_runs():
    out = subprocess.run([sys.executable, "-m", "ago_runtime", "--help"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "Usage" in out.stdout
