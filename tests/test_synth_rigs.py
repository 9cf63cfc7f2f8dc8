"""Issue 38: `ago synth --rig waymo|front` (five Waymo cameras of two image heights / the front one, ground
truth in the Occ3D-Waymo class table and layout) and `--rig nuscenes` unchanged byte for byte."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from ago_runtime.classes import FREE, OCC3D_ID, OCC3D_WAYMO
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.occ3d_waymo import Occ3DWaymoLabels, list_gt_files
from ago_train.synth.config import SynthConfig
from ago_train.synth.generate import generate_scene, write_dataset
from ago_train.synth.rigs import SIDE_HEIGHT_RATIO, WAYMO_CAMERAS, WAYMO_HFOV_DEG
from ago_train.synth.waymo_labels import NUSCENES_TO_WAYMO

TINY = dict(seed=1, num_scenes=1, frames_per_scene=2, image_width=96, image_height=64, grid_shape=(50, 50, 4))
W = {n: OCC3D_WAYMO.id_of(n) for n in OCC3D_WAYMO.names}


def _digest(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(q for q in root.rglob("*") if q.is_file()):
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def test_rig_nuscenes_is_byte_for_byte_the_dataset_before_rigs(tmp_path):
    """The digest of this tiny dataset was taken with the synth code before `--rig` existed (commit 90af580,
    whose ago_train/synth is main's at a2187f0); the default and `rig_name="nuscenes"` still write it."""
    cfg = dict(seed=2, num_scenes=2, frames_per_scene=2, image_width=64, image_height=36, grid_shape=(20, 20, 4),
               val_fraction=0.5)
    write_dataset(SynthConfig(**cfg), tmp_path / "default", progress=False)
    write_dataset(SynthConfig(**cfg, rig_name="nuscenes"), tmp_path / "named", progress=False)
    assert _digest(tmp_path / "default") == _digest(tmp_path / "named") == \
        "9ccc4f81ff47e01d585edd445034f513b48bade43e6519e1c3b80b701b08fdae"


def test_waymo_rig_five_cameras_two_heights_one_focal_length():
    cams = SynthConfig(**TINY, rig_name="waymo").rig()
    assert [c.name for c in cams] == list(WAYMO_CAMERAS)
    side_h = round(64 * SIDE_HEIGHT_RATIO)
    assert [(c.width, c.height) for c in cams] == [(96, 64)] * 3 + [(96, side_h)] * 2
    f = {c.intrinsics[0, 0] for c in cams}
    assert len(f) == 1                                           # same horizontal field of view ...
    hfov = np.degrees(2 * np.arctan(48 / f.pop()))
    assert hfov == pytest.approx(WAYMO_HFOV_DEG)
    # ... looking forward, 45 degrees left/right, 90 degrees left/right (camera z axis in the ego frame)
    yaws = [np.degrees(np.arctan2(c.cam2ego[1, 2], c.cam2ego[0, 2])) for c in cams]
    np.testing.assert_allclose(yaws, [0, 45, -45, 90, -90], atol=1e-9)
    for c in cams:
        c.validate("test")
    front = SynthConfig(**TINY, rig_name="front").rig()
    assert [c.name for c in front] == ["FRONT"]
    with pytest.raises(AgoInputError, match="rig"):
        SynthConfig(**TINY, rig_name="kitti")


@pytest.fixture(scope="module")
def both_frames():
    """The same tiny scene rendered with the nuScenes and the Waymo rig (the world does not depend on the rig)."""
    n = list(generate_scene(SynthConfig(**TINY), 0))
    w = list(generate_scene(SynthConfig(**TINY, rig_name="waymo"), 0))
    return n, w


def test_waymo_ground_truth_is_the_same_world_in_waymo_classes(both_frames):
    refined = {(OCC3D_ID["manmade"], W["sign"]), (OCC3D_ID["manmade"], W["traffic_light"]),
               (OCC3D_ID["manmade"], W["pole"]), (OCC3D_ID["vegetation"], W["tree_trunk"]),
               (OCC3D_ID["bicycle"], W["bicyclist"])}
    seen = set()
    for fn, fw in zip(*both_frames):
        sn, gw = fn["gt"].semantics, fw["gt"]
        assert isinstance(gw, Occ3DWaymoLabels)
        sw = gw.semantics
        assert set(np.unique(sw).tolist()) <= set(OCC3D_WAYMO.ids) | {OCC3D_WAYMO.free_id}
        assert np.array_equal(sn == FREE, sw == OCC3D_WAYMO.free_id)        # same geometry
        assert np.array_equal(fn["gt"].mask_lidar, gw.mask_lidar)          # same LiDAR
        differs = NUSCENES_TO_WAYMO[sn] != sw
        pairs = set(zip(sn[differs].tolist(), sw[differs].tolist()))
        assert pairs <= refined, pairs - refined                           # only the material refinements
        seen |= pairs
        assert set(fw["images"]) == set(WAYMO_CAMERAS)
        assert fw["images"]["SIDE_LEFT"].shape == (round(64 * SIDE_HEIGHT_RATIO), 96, 3)
    assert {W["pole"], W["tree_trunk"]} <= {w for _, w in seen}           # the refinements do happen


def test_waymo_fov_mask_has_no_rear_and_front_rig_sees_ahead_only(both_frames):
    grid = SynthConfig(**TINY).grid()
    xs, ys, _ = grid.axis_centres()
    behind = (xs < -4)[:, None] & (np.abs(ys) < 2)[None, :]
    ahead = (xs > 4)[:, None] & (np.abs(ys) < 2)[None, :]
    for fw in both_frames[1]:
        fov = fw["gt"].mask_fov.astype(bool)
        assert not fov[behind].any() and fov[ahead].any()
        assert (fw["gt"].mask_camera.astype(bool) & ~fov).mean() < 0.01   # seen voxels lie in the field of view
    front = next(iter(generate_scene(SynthConfig(**TINY, rig_name="front"), 0)))
    ffov = front["gt"].mask_fov.astype(bool)
    assert not ffov[(xs < 0)].any() and ffov.sum() < both_frames[1][0]["gt"].mask_fov.sum()


def test_cli_writes_the_occ3d_waymo_layout(tmp_path):
    from typer.testing import CliRunner

    from ago_runtime.cli import app

    out = tmp_path / "w"
    r = CliRunner().invoke(app, ["synth", "--rig", "waymo", "--out", str(out), "--scenes", "2", "--frames", "2",
                                 "--image-size", "64x48", "--grid", "25x25x4"])
    assert r.exit_code == 0, r.output
    files = list_gt_files(out, "training") + list_gt_files(out, "validation")
    assert [(s, f) for s, f, _ in files] == [(0, 0), (0, 1), (0, 0), (0, 1)]
    for _, _, p in files:
        assert Occ3DWaymoLabels.load(p, shape=(25, 25, 4)).shape == (25, 25, 4)
    infos = json.loads((out / "cam_infos.json").read_text())
    assert infos["cameras"] == list(WAYMO_CAMERAS) and sorted(infos["frames"]) == ["0000000", "0000001",
                                                                                   "1000000", "1000001"]
    side = infos["frames"]["1000001"]["cameras"]["SIDE_RIGHT"]
    assert (side["width"], side["height"]) == (64, round(48 * SIDE_HEIGHT_RATIO))
    for k, name in enumerate(WAYMO_CAMERAS):
        img = cv2.imread(str(out / "kitti_format" / "validation" / f"image_{k}" / "1000001.jpg"))
        cam = infos["frames"]["1000001"]["cameras"][name]
        assert img.shape == (cam["height"], cam["width"], 3)
    assert json.loads((out / "splits.json").read_text()) == {"train": ["training/000"], "val": ["validation/000"]}

    front = tmp_path / "f"
    r = CliRunner().invoke(app, ["synth", "--rig", "front", "--out", str(front), "--scenes", "1", "--frames", "1",
                                 "--image-size", "64x48", "--grid", "25x25x4"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (front / "kitti_format" / "training").iterdir()) == ["image_0", "velodyne"]
    bad = CliRunner().invoke(app, ["synth", "--out", str(tmp_path / "bad"), "--rig", "rear"])
    assert bad.exit_code == 2 and "'rear' is not one of" in bad.output   # --rig's Enum: click refuses it
    bad = CliRunner().invoke(app, ["synth", "--out", str(tmp_path / "bad"), "--rig", "waymo", "--sweeps-between", "2"])
    assert isinstance(bad.exception, AgoInputError) and "--sweeps-between" in str(bad.exception)
    assert not (tmp_path / "bad").exists()
