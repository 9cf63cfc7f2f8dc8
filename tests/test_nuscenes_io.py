"""nuScenes-format writer and reader, the safe mmdetection3d info reader, the projection overlay.

Round trip: NuScenesWriter -> NuScenesDataset gives back the arrays, poses and rig; the thirteen tables
link up as nuScenes links them; every kind of bad input is one AgoInputError naming the file.
With ../shared present: the real nuScenes keyframe's LiDAR lands in its six images where it should.
"""

from __future__ import annotations

import io
import json
import os
import pickle
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from ago_runtime.geometry.camera import CAMERA_NAMES, Rig
from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.grid import Grid
from ago_runtime.formats.mmdet3d_info import (convert_mmdet3d_info_to_json, load_info_json, load_mmdet3d_info,
                                      read_mmdet3d_info, safe_load_pickle)
from ago_runtime.formats.nuscenes import NuScenesDataset
from ago_runtime.formats.nuscenes_schema import (CATEGORY_NAMES, TABLE_NAMES, matrix_to_quaternion,
                                         quaternion_to_matrix, record_to_matrix)
from ago_runtime.formats.nuscenes_writer import BoxAnnotation, NuScenesWriter
from ago_runtime.formats.occ3d import Occ3DLabels
from ago_runtime.pictures.projection_overlay import render_depth_overlay
from ago_runtime.pictures.render import RIG_LAYOUT as LAYOUT

from conftest import shared_path

W, H = 64, 36
VERSION = "v1.0-test"
GT_SHAPE = (20, 20, 4)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _smooth_image(rng) -> np.ndarray:
    """Low-frequency colours (JPEG keeps them within a few levels)."""
    small = rng.integers(0, 255, (4, 6, 3)).astype(np.uint8)
    return cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC)


def _write_dataset(root: Path) -> dict:
    """2 scenes x 3 keyframes; returns everything that was given to the writer."""
    rng = np.random.default_rng(7)
    rig = Rig.nuscenes_like(W, H)
    writer = NuScenesWriter(root, VERSION)
    given = {"rig": rig, "samples": []}
    for s in range(2):
        scene = writer.add_scene(f"scene-{s:04d}", f"test scene {s}", "town-a" if s == 0 else "town-b")
        for k in range(3):
            ego2global = np.eye(4)
            ego2global[:3, :3] = _rot_z(0.2 * k + s) @ np.array(
                [[1, 0, 0], [0, np.cos(0.02), -np.sin(0.02)], [0, np.sin(0.02), np.cos(0.02)]])
            ego2global[:3, 3] = [120.0 + 5 * k, 80.0 + 40 * s, 0.1 * k]
            lidar2ego = np.eye(4)
            lidar2ego[:3, :3] = _rot_z(np.pi / 2)
            lidar2ego[:3, 3] = [0.94, 0.0, 1.84]
            images = {c.name: _smooth_image(rng) for c in rig}
            points = (rng.normal(size=(100 + k, 5)) * 10).astype(np.float32)
            boxes = [BoxAnnotation("vehicle.car", "car-1", ego2global[:3, 3] + [10.0 + k, 1.0, 0.8],
                                   np.array([1.9, 4.5, 1.6]), 0.3, np.array([2.0, 0.0]), 25, 4),
                     BoxAnnotation("human.pedestrian.adult", f"walker-{k}", ego2global[:3, 3] + [-6.0, 2.0, 0.9],
                                   np.array([0.6, 0.7, 1.75]), -1.0, np.zeros(2), 3, 2)]
            gt = Occ3DLabels(rng.integers(0, 18, GT_SHAPE, dtype=np.uint8),
                             rng.integers(0, 2, GT_SHAPE, dtype=np.uint8), rng.integers(0, 2, GT_SHAPE, dtype=np.uint8))
            extras = {"semantic": {c.name: rng.integers(0, 18, (H, W), dtype=np.uint8) for c in rig},
                      "depth": {c.name: np.round(rng.uniform(0, 90, (H, W)), 2).astype(np.float32) for c in rig}}
            timestamp = 1_600_000_000_000_000 + s * 100_000_000 + k * 500_000
            token = writer.add_sample(scene, timestamp, ego2global, rig, images, points, lidar2ego, boxes, gt, extras)
            given["samples"].append(dict(token=token, scene=f"scene-{s:04d}", timestamp=timestamp,
                                         ego2global=ego2global, lidar2ego=lidar2ego, images=images, points=points,
                                         boxes=boxes, gt=gt, extras=extras))
    writer.close({"train": ["scene-0000"], "val": ["scene-0001"]})
    return given


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    root = tmp_path_factory.mktemp("nuscenes") / "ds"
    given = _write_dataset(root)
    return root, given


@pytest.fixture
def copy_of(written, tmp_path):
    root, _ = written
    dst = tmp_path / "ds"
    shutil.copytree(root, dst)
    return dst


def _tables(root: Path) -> dict[str, list[dict]]:
    return {name: json.loads((root / VERSION / f"{name}.json").read_text()) for name in TABLE_NAMES}


# ---------------------------------------------------------------------------- writer output
def test_quaternion_helpers_invert_each_other():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        r = quaternion_to_matrix(q)
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(r), 1.0)
        assert np.allclose(matrix_to_quaternion(r), q, atol=1e-12)
    # rotation of 90 deg about z: x axis -> y axis, quaternion [cos 45, 0, 0, sin 45]
    r = quaternion_to_matrix([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    assert np.allclose(r @ [1, 0, 0], [0, 1, 0])


def test_all_thirteen_tables_link_up(written):
    root, given = written
    t = _tables(root)
    assert set(t) == set(TABLE_NAMES)
    by = {name: {r["token"]: r for r in recs} for name, recs in t.items()}
    for name, recs in t.items():
        assert len(by[name]) == len(recs), f"duplicate tokens in {name}"

    # scenes: first/last/nbr_samples agree with the sample chain
    assert [s["name"] for s in t["scene"]] == ["scene-0000", "scene-0001"]
    for scene in t["scene"]:
        chain, tok = [], scene["first_sample_token"]
        while tok:
            sample = by["sample"][tok]
            assert sample["scene_token"] == scene["token"]
            if sample["prev"]:
                assert by["sample"][sample["prev"]]["next"] == tok
            chain.append(tok)
            tok = sample["next"]
        assert len(chain) == scene["nbr_samples"] == 3 and chain[-1] == scene["last_sample_token"]
        assert by["sample"][chain[0]]["prev"] == ""
        assert scene["log_token"] in by["log"]
        assert [by["sample"][c]["timestamp"] for c in chain] == sorted(by["sample"][c]["timestamp"] for c in chain)

    # sample_data: seven keyframes per sample, valid references, files exist, prev/next per channel
    channel = {cs["token"]: by["sensor"][cs["sensor_token"]]["channel"] for cs in t["calibrated_sensor"]}
    per_sample = {}
    for sd in t["sample_data"]:
        assert sd["sample_token"] in by["sample"] and sd["ego_pose_token"] in by["ego_pose"]
        assert sd["is_key_frame"] is True and (root / sd["filename"]).is_file()
        ch = channel[sd["calibrated_sensor_token"]]
        per_sample.setdefault(sd["sample_token"], []).append(ch)
        assert sd["filename"].startswith(f"samples/{ch}/") and f"__{ch}__{sd['timestamp']}" in sd["filename"]
        if ch == "LIDAR_TOP":
            assert (sd["fileformat"], sd["width"], sd["height"]) == ("pcd", 0, 0)
            assert sd["filename"].endswith(".pcd.bin")
        else:
            assert (sd["fileformat"], sd["width"], sd["height"]) == ("jpg", W, H)
        for link, back in (("prev", "next"), ("next", "prev")):
            if sd[link]:
                other = by["sample_data"][sd[link]]
                assert other[back] == sd["token"] and channel[other["calibrated_sensor_token"]] == ch
        assert by["ego_pose"][sd["ego_pose_token"]]["timestamp"] == sd["timestamp"]
    assert len(per_sample) == 6
    assert all(sorted(chs) == sorted([*CAMERA_NAMES, "LIDAR_TOP"]) for chs in per_sample.values())

    # calibrated sensors: unit quaternions [w, x, y, z], intrinsics only for cameras
    for cs in t["calibrated_sensor"]:
        assert np.isclose(np.linalg.norm(cs["rotation"]), 1.0)
        sensor = by["sensor"][cs["sensor_token"]]
        assert (len(cs["camera_intrinsic"]) == 3) == (sensor["modality"] == "camera")
    assert sorted(s["channel"] for s in t["sensor"]) == sorted([*CAMERA_NAMES, "LIDAR_TOP"])

    # annotations and instances
    n_boxes = sum(len(s["boxes"]) for s in given["samples"])
    assert len(t["sample_annotation"]) == n_boxes
    for inst in t["instance"]:
        assert inst["category_token"] in by["category"]
        chain, tok = [], inst["first_annotation_token"]
        while tok:
            ann = by["sample_annotation"][tok]
            assert ann["instance_token"] == inst["token"]
            chain.append(tok)
            tok = ann["next"]
        assert len(chain) == inst["nbr_annotations"] and chain[-1] == inst["last_annotation_token"]
    assert sorted(i["nbr_annotations"] for i in t["instance"]) == [1, 1, 1, 1, 1, 1, 3, 3]
    for ann in t["sample_annotation"]:
        assert ann["visibility_token"] in by["visibility"]
        assert all(a in by["attribute"] for a in ann["attribute_tokens"]) and len(ann["attribute_tokens"]) == 1
        assert ann["sample_token"] in by["sample"]
    categories = [c["name"] for c in t["category"]]
    assert categories == list(CATEGORY_NAMES) and [c["index"] for c in t["category"]] == list(range(32))
    assert sorted(v["token"] for v in t["visibility"]) == ["1", "2", "3", "4"]

    # logs and maps: every log on exactly one map, whose mask is drivable at the ego positions
    assert sorted(log["location"] for log in t["log"]) == ["town-a", "town-b"]
    map_of = {lt: m for m in t["map"] for lt in m["log_tokens"]}
    assert set(map_of) == set(by["log"])
    for scene in t["scene"]:
        m = map_of[scene["log_token"]]
        mask = cv2.imread(str(root / m["filename"]), cv2.IMREAD_UNCHANGED)
        assert mask.dtype == np.uint8 and mask.ndim == 2
        pose = by["ego_pose"][by["sample_data"][next(
            sd["token"] for sd in t["sample_data"] if sd["sample_token"] == scene["first_sample_token"])]["ego_pose_token"]]
        x, y = pose["translation"][:2]
        assert mask[int(mask.shape[0] - y / 0.1), int(x / 0.1)] == 255
        assert mask[int(mask.shape[0] - (y + 30) / 0.1), int(x / 0.1)] == 0   # 30 m to the side: not road

    assert json.loads((root / "splits.json").read_text()) == {"train": ["scene-0000"], "val": ["scene-0001"]}


def test_annotation_records_keep_the_boxes(written):
    root, given = written
    t = _tables(root)
    anns = {(a["sample_token"], a["translation"][0]): a for a in t["sample_annotation"]}
    for s in given["samples"]:
        for box in s["boxes"]:
            ann = anns[(s["token"], float(box.center[0]))]
            assert np.allclose(ann["translation"], box.center) and np.allclose(ann["size"], box.size)
            r = quaternion_to_matrix(ann["rotation"])
            assert np.isclose(np.arctan2(r[1, 0], r[0, 0]), box.yaw)
            assert ann["num_lidar_pts"] == box.num_lidar_pts and ann["visibility_token"] == str(box.visibility)


def test_writer_is_deterministic(written, tmp_path):
    root, _ = written
    again = tmp_path / "again"
    _write_dataset(again)
    files = sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    assert len(files) > 100
    for rel in files:
        assert (root / rel).read_bytes() == (again / rel).read_bytes(), rel
    assert not list(root.rglob("*.tmp*")), "temporary files left behind"


def test_writer_refuses_bad_samples(tmp_path):
    rig = Rig.nuscenes_like(W, H)
    writer = NuScenesWriter(tmp_path / "ds")
    scene = writer.add_scene("s")
    images = {c.name: np.zeros((H, W, 3), np.uint8) for c in rig}
    pts = np.zeros((3, 5), np.float32)
    with pytest.raises(AgoInputError, match="CAM_BACK image must be"):
        writer.add_sample(scene, 1, np.eye(4), rig, {**images, "CAM_BACK": np.zeros((H, W), np.uint8)}, pts, np.eye(4))
    with pytest.raises(AgoInputError, match="unknown nuScenes category"):
        writer.add_sample(scene, 2, np.eye(4), rig, images, pts, np.eye(4),
                          [BoxAnnotation("car", "a", np.zeros(3), np.ones(3), 0.0)])
    writer.add_sample(scene, 10, np.eye(4), rig, images, pts, np.eye(4))
    with pytest.raises(AgoInputError, match="timestamps must increase"):
        writer.add_sample(scene, 10, np.eye(4), rig, images, pts, np.eye(4))
    bad_pose = np.eye(4)
    bad_pose[0, 0] = 2.0
    with pytest.raises(AgoInputError, match="ego2global"):
        writer.add_sample(scene, 20, bad_pose, rig, images, pts, np.eye(4))
    with pytest.raises(AgoInputError, match="lidar_points"):
        writer.add_sample(scene, 30, np.eye(4), rig, images, np.zeros((3, 4), np.float32), np.eye(4))
    with pytest.raises(AgoInputError, match="not written"):
        writer.close({"train": ["s", "nope"]})


# ---------------------------------------------------------------------------- reader
def test_round_trip_gives_back_what_was_written(written):
    root, given = written
    ds = NuScenesDataset(root)
    assert ds.version == VERSION and len(ds) == 6
    assert ds.sample_tokens == [s["token"] for s in given["samples"]]
    for i, s in enumerate(given["samples"]):
        assert ds.index_of(s["token"]) == i and ds.scene_of(i) == s["scene"]
        f = ds[i]
        assert (f.token, f.scene, f.timestamp) == (s["token"], s["scene"], s["timestamp"])
        assert np.allclose(f.ego2global, s["ego2global"], atol=1e-9)
        assert len(f.sweeps) == 1
        assert np.array_equal(f.lidar.points, s["points"]) and f.lidar.points.dtype == np.float32
        assert np.allclose(f.lidar.lidar2ego, s["lidar2ego"], atol=1e-9)
        assert f.lidar.timestamp == s["timestamp"] and Path(f.lidar.path).is_file()
        for cam, ref in zip(f.rig, given["rig"]):
            assert cam.name == ref.name and (cam.width, cam.height) == (ref.width, ref.height)
            assert np.allclose(cam.intrinsics, ref.intrinsics, atol=1e-9)
            assert np.allclose(cam.cam2ego, ref.cam2ego, atol=1e-9)
            img = f.images[cam.name]
            assert img.shape == (H, W, 3) and img.dtype == np.uint8
            decoded = cv2.imread(f.image_paths[cam.name])[..., ::-1]
            assert np.array_equal(img, decoded)                 # RGB, exactly what the JPEG holds
            error = np.abs(img.astype(int) - s["images"][cam.name]).mean()       # JPEG q95, 4:2:0 chroma
            swapped = np.abs(img[..., ::-1].astype(int) - s["images"][cam.name]).mean()
            assert error < 4.0 and swapped > 10 * error
            assert np.array_equal(f.extras["semantic"][cam.name], s["extras"]["semantic"][cam.name])
            depth = f.extras["depth"][cam.name]
            assert depth.dtype == np.float32
            assert np.abs(depth - s["extras"]["depth"][cam.name]).max() <= 0.0051
        for k in ("semantics", "mask_lidar", "mask_camera"):
            assert np.array_equal(getattr(f.gt, k), getattr(s["gt"], k))


def test_reader_options_sweeps_splits_neighbours(written):
    root, given = written
    ds = NuScenesDataset(root, load_images=False, load_extras=False, num_sweeps=5)
    f = ds[2]
    assert f.images == {} and f.extras == {} and set(f.image_paths) == set(CAMERA_NAMES)
    assert (f.rig["CAM_FRONT"].width, f.rig["CAM_FRONT"].height) == (W, H)
    # sweeps walk the LIDAR_TOP prev chain within the scene, nearest first
    assert [sw.timestamp for sw in f.sweeps] == [given["samples"][j]["timestamp"] for j in (2, 1, 0)]
    assert np.array_equal(f.sweeps[1].points, given["samples"][1]["points"])
    assert np.allclose(f.sweeps[1].ego2global, given["samples"][1]["ego2global"], atol=1e-9)
    assert len(ds[3].sweeps) == 1  # first sample of scene-0001: nothing earlier
    assert ds.split("train") == [0, 1, 2] and ds.split("val") == [3, 4, 5] and ds.split("all") == list(range(6))
    assert ds.neighbours(1, 2, 1) == [2, 0]
    assert ds.neighbours(0, 2, 1) == [1, 2]          # clipped at the scene start, filled from the other side
    assert ds.neighbours(2, 5, 1) == [1, 0]          # never crosses into scene-0001
    assert ds.neighbours(3, 3, 2) == [5]
    assert ds.neighbours(4, 0, 1) == []
    assert NuScenesDataset(root, gts_root=root / "nowhere")[0].gt is None


def test_camera_ego_motion_compensation(copy_of):
    """A camera whose own ego pose is 1 m ahead of the LiDAR's sits 1 m further forward in the frame."""
    ds = NuScenesDataset(copy_of, load_images=False, load_extras=False)
    before = ds[0]
    tables = _tables(copy_of)
    cs = {c["token"]: c for c in tables["calibrated_sensor"]}
    sensors = {s["token"]: s["channel"] for s in tables["sensor"]}
    front = next(sd for sd in tables["sample_data"] if sd["sample_token"] == before.token
                 and sensors[cs[sd["calibrated_sensor_token"]]["sensor_token"]] == "CAM_FRONT")
    poses = tables["ego_pose"]
    pose = next(p for p in poses if p["token"] == front["ego_pose_token"])
    ahead = record_to_matrix(pose)[:3, :3] @ np.array([1.0, 0.0, 0.0])   # 1 m along the car's own x
    pose["translation"] = list(np.asarray(pose["translation"]) + ahead)
    (copy_of / VERSION / "ego_pose.json").write_text(json.dumps(poses))
    moved = NuScenesDataset(copy_of, load_images=False, load_extras=False)[0]
    shift = moved.rig["CAM_FRONT"].cam2ego[:3, 3] - before.rig["CAM_FRONT"].cam2ego[:3, 3]
    assert np.allclose(shift, [1.0, 0.0, 0.0], atol=1e-9)
    assert np.allclose(moved.rig["CAM_BACK"].cam2ego, before.rig["CAM_BACK"].cam2ego)
    raw = NuScenesDataset(copy_of, load_images=False, load_extras=False, compensate_ego_motion=False)[0]
    assert np.allclose(raw.rig["CAM_FRONT"].cam2ego, before.rig["CAM_FRONT"].cam2ego)


def test_missing_table(copy_of):
    (copy_of / VERSION / "ego_pose.json").unlink()
    with pytest.raises(AgoInputError) as e:
        NuScenesDataset(copy_of)
    assert e.value.path.endswith("ego_pose.json") and "missing" in e.value.problem


def test_table_pointing_at_missing_file(copy_of):
    jpg = next((copy_of / "samples" / "CAM_BACK_LEFT").glob("*.jpg"))
    jpg.unlink()
    ds = NuScenesDataset(copy_of)
    with pytest.raises(AgoInputError) as e:
        for i in range(len(ds)):
            ds[i]
    assert e.value.path == str(jpg) and "missing" in e.value.problem
    lidar = Path(ds[5].lidar.path)  # scene-0001's images are intact
    lidar.unlink()
    with pytest.raises(AgoInputError) as e:
        ds[5]
    assert e.value.path == str(lidar) and "missing" in e.value.problem


def test_missing_camera_for_a_sample(copy_of):
    path = copy_of / VERSION / "sample_data.json"
    records = json.loads(path.read_text())
    cs = {c["token"]: c for c in json.loads((copy_of / VERSION / "calibrated_sensor.json").read_text())}
    sensors = {s["token"]: s["channel"] for s in json.loads((copy_of / VERSION / "sensor.json").read_text())}
    victim = next(r for r in records if sensors[cs[r["calibrated_sensor_token"]]["sensor_token"]] == "CAM_BACK")
    path.write_text(json.dumps([r for r in records if r is not victim]))
    with pytest.raises(AgoInputError) as e:
        NuScenesDataset(copy_of)
    assert e.value.path == str(path) and "CAM_BACK" in e.value.problem and victim["sample_token"] in e.value.problem


def test_broken_records(copy_of):
    path = copy_of / VERSION / "ego_pose.json"
    poses = json.loads(path.read_text())
    path.write_text(json.dumps(poses[1:]))            # a sample_data now points at a missing ego_pose
    ds = NuScenesDataset(copy_of, load_images=False)
    with pytest.raises(AgoInputError) as e:
        for i in range(len(ds)):
            ds[i]
    assert e.value.path.endswith("sample_data.json") and poses[0]["token"] in e.value.problem
    path = copy_of / VERSION / "sample.json"
    samples = json.loads(path.read_text())
    del samples[2]["timestamp"]
    path.write_text(json.dumps(samples))
    with pytest.raises(AgoInputError) as e:
        NuScenesDataset(copy_of)
    assert e.value.path == str(copy_of / VERSION / "sample.json") and "timestamp" in e.value.problem
    path.write_text("[{]")
    with pytest.raises(AgoInputError, match="not valid JSON"):
        NuScenesDataset(copy_of)


@pytest.mark.parametrize("damage", ["truncate", "garbage"])
def test_corrupt_jpeg(copy_of, damage):
    ds = NuScenesDataset(copy_of)
    jpg = Path(ds[0].image_paths["CAM_FRONT"])
    data = jpg.read_bytes()
    if damage == "truncate":
        jpg.write_bytes(data[: len(data) // 2])
    else:  # right markers, nonsense inside
        jpg.write_bytes(b"\xff\xd8" + bytes(range(256)) * 4 + b"\xff\xd9")
    with pytest.raises(AgoInputError) as e:
        ds[0]
    assert e.value.path == str(jpg)
    assert ("truncated" if damage == "truncate" else "corrupt") in e.value.problem


def test_lidar_size_not_multiple_of_20(copy_of):
    ds = NuScenesDataset(copy_of, load_images=False)
    lidar = Path(ds[1].lidar.path)
    with open(lidar, "ab") as f:
        f.write(b"\x00" * 8)
    with pytest.raises(AgoInputError) as e:
        ds[1]
    assert e.value.path == str(lidar) and "multiple of 20" in e.value.problem


def test_labels_with_the_wrong_shape(copy_of):
    token = NuScenesDataset(copy_of).sample_tokens[0]
    labels = copy_of / "gts" / "scene-0000" / token / "labels.npz"
    assert NuScenesDataset(copy_of, grid=Grid.with_shape(GT_SHAPE), load_images=False)[0].gt.shape == GT_SHAPE
    with pytest.raises(AgoInputError) as e:
        NuScenesDataset(copy_of, grid=Grid.occ3d(), load_images=False)[0]
    assert e.value.path == str(labels) and "(200, 200, 16)" in e.value.problem
    np.savez(labels, semantics=np.zeros((4, 4, 2), np.uint8), mask_lidar=np.zeros((4, 4, 3), np.uint8),
             mask_camera=np.zeros((4, 4, 2), np.uint8))
    with pytest.raises(AgoInputError) as e:
        NuScenesDataset(copy_of, load_images=False)[0]
    assert e.value.path == str(labels)


def test_bad_splits_and_versions(copy_of):
    ds = NuScenesDataset(copy_of, load_images=False)
    with pytest.raises(AgoInputError) as e:
        ds.split("test")
    assert e.value.path == str(copy_of / "splits.json") and "'test'" in e.value.problem
    (copy_of / "splits.json").write_text(json.dumps({"train": ["scene-0000", "scene-9999"]}))
    with pytest.raises(AgoInputError, match="scene-9999"):
        ds.split("train")
    shutil.copytree(copy_of / VERSION, copy_of / "v1.0-other")
    with pytest.raises(AgoInputError, match="several"):
        NuScenesDataset(copy_of)
    assert len(NuScenesDataset(copy_of, version="v1.0-other", load_images=False)) == 6
    with pytest.raises(AgoInputError, match="not found"):
        NuScenesDataset(copy_of / "nothing")


# ---------------------------------------------------------------------------- mmdetection3d info files
class _Evil:
    def __init__(self, command: str):
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


def test_safe_unpickler_refuses_code(tmp_path):
    marker = tmp_path / "pwned"
    for payload in ({"data_list": [_Evil(f"touch {marker}")]}, [eval], {"x": Path("/etc")}):
        bad = tmp_path / "evil.pkl"
        bad.write_bytes(pickle.dumps(payload))
        with pytest.raises(AgoInputError) as e:
            safe_load_pickle(bad)
        assert e.value.path == str(bad) and "refusing to unpickle" in e.value.problem
    assert not marker.exists()
    # numpy arrays (old and new protocols), numpy scalars and plain containers are fine
    good = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.float64(2.5), "c": [1, (2, 3)],
            "d": np.array([True, False]), "e": {"f": np.int64(7)}}
    for protocol in (2, 4, 5):
        path = tmp_path / f"good{protocol}.pkl"
        path.write_bytes(pickle.dumps(good, protocol=protocol))
        back = safe_load_pickle(path)
        assert np.array_equal(back["a"], good["a"]) and back["a"].dtype == np.float32
        assert back["b"] == 2.5 and back["c"] == [1, (2, 3)] and back["e"]["f"] == 7
    truncated = tmp_path / "cut.pkl"
    truncated.write_bytes(pickle.dumps(good)[:40])
    with pytest.raises(AgoInputError, match="not a readable pickle"):
        safe_load_pickle(truncated)


def test_info_frames_from_written_dataset_layout(written, tmp_path):
    """An info dict in mmdet3d 1.1 layout built from the written dataset reads back the same frame."""
    root, given = written
    f = NuScenesDataset(root, load_extras=False)[0]
    info = {"metainfo": {"info_version": "1.1"}, "data_list": [{
        "token": f.token, "timestamp": f.timestamp / 1e6, "ego2global": f.ego2global,
        "lidar_points": {"lidar_path": Path(f.lidar.path).name, "lidar2ego": f.lidar.lidar2ego, "num_pts_feats": 5},
        "images": {c.name: {"img_path": Path(f.image_paths[c.name]).name, "cam2img": c.intrinsics,
                            "cam2ego": c.cam2ego} for c in f.rig}}]}
    pkl = tmp_path / "info.pkl"
    pkl.write_bytes(pickle.dumps(info))
    (g,) = load_mmdet3d_info(pkl, data_root=root)
    assert g.token == f.token and g.timestamp == f.timestamp
    assert np.array_equal(g.lidar.points, f.lidar.points) and np.allclose(g.ego2global, f.ego2global)
    for a, b in zip(g.rig, f.rig):
        assert np.allclose(a.intrinsics, b.intrinsics) and np.allclose(a.cam2ego, b.cam2ego)
        assert np.array_equal(g.images[a.name], f.images[a.name])
    del info["data_list"][0]["images"]["CAM_BACK_RIGHT"]
    pkl.write_bytes(pickle.dumps(info))
    with pytest.raises(AgoInputError, match="CAM_BACK_RIGHT"):
        load_mmdet3d_info(pkl, data_root=root)


# ---------------------------------------------------------------------------- the real keyframe
@pytest.fixture(scope="module")
def real_frame():
    root = shared_path("nuscenes-sample")
    (frame,) = load_mmdet3d_info(root / "mmdet3d_info.pkl")
    return root, frame


def test_real_info_reads_as_nuscenes_says(real_frame):
    root, f = real_frame
    assert f.token == "ca9a282c9e77460f8360f564131a8af5"
    assert f.timestamp == 1532402927647951
    assert all(f.images[c].shape == (900, 1600, 3) for c in CAMERA_NAMES)
    assert f.lidar.points.shape[1] == 5 and len(f.lidar.points) > 20000
    # cam2ego is the camera in the keyframe (LiDAR) ego frame: it reproduces the info's own lidar2cam,
    # which includes the ego motion between the LiDAR sweep and each camera exposure
    info = read_mmdet3d_info(root / "mmdet3d_info.pkl")["data_list"][0]
    (raw,) = load_mmdet3d_info(root / "mmdet3d_info.pkl", compensate_ego_motion=False)
    speeds = []
    for cam, raw_cam in zip(f.rig, raw.rig):
        lidar2cam = np.asarray(info["images"][cam.name]["lidar2cam"])
        assert np.allclose(cam.ego2cam @ f.lidar.lidar2ego, lidar2cam, atol=1e-6), cam.name
        assert np.allclose(raw_cam.cam2ego, np.asarray(info["images"][cam.name]["cam2ego"]))
        # the calibrated cam2ego differs by the car's motion: little rotation, a shift of speed * dt
        assert np.abs(cam.cam2ego[:3, :3] - raw_cam.cam2ego[:3, :3]).max() < 3e-3
        dt = abs(f.timestamp / 1e6 - info["images"][cam.name]["timestamp"])
        speeds.append(np.linalg.norm(cam.cam2ego[:3, 3] - raw_cam.cam2ego[:3, 3]) / dt)
    assert 3.0 < np.median(speeds) < 20.0 and np.ptp(speeds) < 0.1 * np.median(speeds), speeds


def test_real_lidar_projects_into_the_six_cameras(real_frame):
    _, f = real_frame
    points_ego = f.lidar.points_ego()
    for cam in f.rig:
        uv, depth, ok = cam.project(points_ego)
        assert ok.sum() > 1500, (cam.name, ok.sum())
        assert np.all(depth[ok] > 0)
        assert 5.0 < np.median(depth[ok]) < 40.0, (cam.name, np.median(depth[ok]))
    # points ahead of the car, in a narrow cone, land in CAM_FRONT and in no rear camera
    x, y = points_ego[:, 0], points_ego[:, 1]
    ahead = (x > 5) & (np.abs(y) < 0.3 * x)
    in_front = f.rig["CAM_FRONT"].project(points_ego[ahead])[2]
    assert ahead.sum() > 1000 and in_front.mean() > 0.7
    assert f.rig["CAM_BACK"].project(points_ego[ahead])[2].sum() == 0


def test_real_overlay_png_and_json_conversion(real_frame, tmp_path):
    root, f = real_frame
    out = tmp_path / "overlay.png"
    picture = render_depth_overlay(f, out, tile_width=400)
    on_disk = cv2.imread(str(out))[..., ::-1]
    assert np.array_equal(on_disk, picture) and picture.shape == (2 * 225, 3 * 400, 3)
    # the overlay changed pixels of every tile (points drawn), the layout puts CAM_FRONT top-middle
    for r, row in enumerate(LAYOUT):
        for c, name in enumerate(row):
            plain = cv2.resize(f.images[name], (400, 225), interpolation=cv2.INTER_AREA)
            tile = picture[r * 225:(r + 1) * 225, c * 400:(c + 1) * 400]
            changed = np.any(tile != plain, axis=-1).mean()
            assert 0.02 < changed < 0.6, (name, changed)
    assert LAYOUT[0][1] == "CAM_FRONT"

    js = tmp_path / "info.json"
    convert_mmdet3d_info_to_json(root / "mmdet3d_info.pkl", js)
    (g,) = load_info_json(js, data_root=root)
    assert g.token == f.token and np.array_equal(g.lidar.points, f.lidar.points)
    assert np.allclose(g.ego2global, f.ego2global) and np.allclose(g.lidar.lidar2ego, f.lidar.lidar2ego)
    for a, b in zip(g.rig, f.rig):
        assert np.allclose(a.intrinsics, b.intrinsics) and np.allclose(a.cam2ego, b.cam2ego)


def test_jpeg_reader_gives_rgb(tmp_path):
    """read_jpeg_rgb turns cv2's BGR into RGB (a contiguous array): a red-left, blue-right picture, encoded the way
    the writers encode (RGB -> BGR -> JPEG), reads back red on the left, blue on the right."""
    from ago_runtime.formats.nuscenes import read_jpeg_rgb

    rgb = np.zeros((64, 96, 3), np.uint8)
    rgb[:, :48, 0] = 255   # red
    rgb[:, 48:, 2] = 255   # blue
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    (tmp_path / "a.jpg").write_bytes(jpg.tobytes())
    back = read_jpeg_rgb(tmp_path / "a.jpg")
    assert back.shape == (64, 96, 3) and back.flags["C_CONTIGUOUS"]
    assert back[32, 10, 0] > 200 and back[32, 10, 2] < 60      # red on the left
    assert back[32, 80, 2] > 200 and back[32, 80, 0] < 60      # blue on the right
