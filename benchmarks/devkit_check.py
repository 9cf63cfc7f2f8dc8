"""Open a dataset written by `ago_runtime.formats.nuscenes_writer` with the official nuscenes-devkit.

Run it with a Python that has nuscenes-devkit (a throwaway venv: nuscenes-devkit is NOT a
dependency of ago), e.g.

    python -m venv --system-site-packages /tmp/devkit
    /tmp/devkit/bin/pip install --no-deps nuscenes-devkit
    /tmp/devkit/bin/pip install pyquaternion matplotlib shapely Pillow scikit-learn
    /tmp/devkit/bin/python -m benchmarks.devkit_check --version v1.0-mini --dataroot /tmp/ds

With `--write`, the script first writes a small dataset there itself (needs ago importable, i.e.
run from the repository root), then moves every camera's ego pose 0.3 m / 0.5 deg away from the
LiDAR's, as real nuScenes cameras have their own poses. It loads the tables with `NuScenes(version, dataroot)`, walks every
scene's sample chain, calls `get_sample_data` for each camera and the LiDAR of each sample, reads
the boxes, checks that every box centre the devkit moves into a camera frame (pyquaternion) lands
where ago's own pose matrices put it, checks that the devkit's `map_pointcloud_to_image` projects
the LiDAR exactly where `NuScenesDataset` + `Camera.project` do, reads the map mask, and prints a summary. Any failure raises.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def write_dataset(root: Path, version: str) -> None:
    from ago_runtime.geometry.camera import Rig
    from ago_runtime.formats.nuscenes_writer import BoxAnnotation, NuScenesWriter
    from ago_runtime.formats.nuscenes_schema import record_to_matrix
    from ago_runtime.formats.occ3d import Occ3DLabels

    rng = np.random.default_rng(0)
    rig = Rig.nuscenes_like(320, 180)
    writer = NuScenesWriter(root, version)
    for s in range(2):
        scene = writer.add_scene(f"scene-{s:04d}", "devkit check", "synthetic-town")
        for k in range(4):
            yaw = 0.1 * k
            pose = np.eye(4)
            pose[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
            pose[:3, 3] = [300.0 + 4 * k, 200.0 + 100 * s, 0.0]
            images = {c.name: rng.integers(0, 255, (180, 320, 3), dtype=np.uint8) for c in rig}
            points = (rng.normal(size=(2000, 5)) * 10).astype(np.float32)
            lidar2ego = np.eye(4)
            lidar2ego[:3, 3] = [0.94, 0.0, 1.84]
            forward = pose[:3, :3] @ np.array([12.0, 0.0, 0.0])
            boxes = [BoxAnnotation("vehicle.car", "car", pose[:3, 3] + forward + [0, 0, 0.8],
                                   np.array([1.9, 4.6, 1.6]), yaw, np.array([4.0, 0.0]), 40, 4),
                     BoxAnnotation("human.pedestrian.adult", "walker", pose[:3, 3] + [-8.0, 3.0, 0.9],
                                   np.array([0.6, 0.7, 1.75]), 0.0, np.zeros(2), 5, 3)]
            gt = Occ3DLabels(*(rng.integers(0, 2, (20, 20, 4), dtype=np.uint8) for _ in range(3)))
            writer.add_sample(scene, 1_600_000_000_000_000 + s * 10**8 + k * 500_000, pose, rig, images,
                              points, lidar2ego, boxes, gt)
    writer.close({"train": ["scene-0000"], "val": ["scene-0001"]})

    # Make it look like real nuScenes, where each camera fires at its own time and has its own ego pose:
    # move every camera's ego_pose record 0.3 m forward and turn it 0.5 deg (the LiDAR's stays).
    import json

    table = root / version
    sensors = {r["token"]: r["channel"] for r in json.loads((table / "sensor.json").read_text())}
    channel = {r["token"]: sensors[r["sensor_token"]] for r in json.loads((table / "calibrated_sensor.json").read_text())}
    camera_pose_tokens = {sd["ego_pose_token"] for sd in json.loads((table / "sample_data.json").read_text())
                          if channel[sd["calibrated_sensor_token"]] != "LIDAR_TOP"}
    poses = json.loads((table / "ego_pose.json").read_text())
    turn = np.deg2rad(0.5)
    for pose in poses:
        if pose["token"] in camera_pose_tokens:
            w, x, y, z = pose["rotation"]  # compose with a yaw of `turn` (quaternion product q * dq)
            c, s = np.cos(turn / 2), np.sin(turn / 2)
            pose["rotation"] = [w * c - z * s, x * c + y * s, y * c - x * s, w * s + z * c]
            r = record_to_matrix(pose)
            pose["translation"] = list(np.asarray(pose["translation"]) + r[:3, :3] @ [0.3, 0.0, 0.0])
    (table / "ego_pose.json").write_text(json.dumps(poses))


def check(dataroot: Path, version: str) -> None:
    from nuscenes.nuscenes import NuScenes
    from nuscenes.utils.geometry_utils import view_points

    from ago_runtime.formats.nuscenes_schema import record_to_matrix

    t0 = time.time()
    nusc = NuScenes(version=version, dataroot=str(dataroot), verbose=True)
    n_samples = n_sd = n_boxes = n_boxes_in_cam = 0
    for scene in nusc.scene:
        token = scene["first_sample_token"]
        walked = []
        while token:
            sample = nusc.get("sample", token)
            walked.append(token)
            assert sample["scene_token"] == scene["token"]
            for channel, sd_token in sample["data"].items():
                path, boxes, intrinsic = nusc.get_sample_data(sd_token)
                assert Path(path).is_file(), path
                n_sd += 1
                sd = nusc.get("sample_data", sd_token)
                if sd["sensor_modality"] == "camera":
                    assert intrinsic.shape == (3, 3)
                    # ago's own matrices (from the same records) must put each box where the devkit does.
                    cam2ego = record_to_matrix(nusc.get("calibrated_sensor", sd["calibrated_sensor_token"]))
                    ego2global = record_to_matrix(nusc.get("ego_pose", sd["ego_pose_token"]))
                    global2cam = np.linalg.inv(ego2global @ cam2ego)
                    for box in boxes:
                        centre = np.array(nusc.get("sample_annotation", box.token)["translation"])
                        ours = global2cam[:3, :3] @ centre + global2cam[:3, 3]
                        assert np.allclose(ours, box.center, atol=1e-6), (ours, box.center)
                        uv = view_points(box.center[:, None], intrinsic, normalize=True)[:2, 0]
                        n_boxes_in_cam += int(0 <= uv[0] < sd["width"] and 0 <= uv[1] < sd["height"])
                else:
                    pts = np.fromfile(path, dtype=np.float32)
                    assert pts.size % 5 == 0
            anns = [nusc.get("sample_annotation", t) for t in sample["anns"]]
            for ann in anns:
                box = nusc.get_box(ann["token"])
                velocity = nusc.box_velocity(ann["token"])
                assert box.wlh.shape == (3,) and velocity.shape == (3,)
                n_boxes += 1
            token = sample["next"]
            n_samples += 1
        assert len(walked) == scene["nbr_samples"], (len(walked), scene["nbr_samples"])
        assert walked[-1] == scene["last_sample_token"]
        log = nusc.get("log", scene["log_token"])
        mask = nusc.get("map", log["map_token"])["mask"].mask()
        assert mask.ndim == 2 and mask.max() == 255
    # the devkit's LiDAR-into-image projection (pyquaternion pose chain) against ago's reader + Camera.project
    from ago_runtime.formats.nuscenes import NuScenesDataset

    dataset = NuScenesDataset(dataroot, version, load_images=False, load_extras=False)
    n_compared, max_px, max_m = 0, 0.0, 0.0
    for sample in nusc.sample:
        frame = dataset[dataset.index_of(sample["token"])]
        points_ego = frame.lidar.points_ego()
        for cam in frame.rig:
            uvz, depth, _ = nusc.explorer.map_pointcloud_to_image(sample["data"]["LIDAR_TOP"], sample["data"][cam.name])
            uv, d, ok = cam.project(points_ego)
            # the devkit keeps depth > 1 m and 1 px inside the border
            keep = ok & (d > 1.0) & (uv[:, 0] > 1) & (uv[:, 0] < cam.width - 1) & (uv[:, 1] > 1) & (uv[:, 1] < cam.height - 1)
            assert keep.sum() == uvz.shape[1], (cam.name, keep.sum(), uvz.shape)
            if keep.any():  # the devkit works in float32: agreement to ~1e-3 px
                max_px = max(max_px, float(np.abs(uv[keep] - uvz[:2].T).max()))
                max_m = max(max_m, float(np.abs(d[keep] - depth).max()))
            n_compared += int(keep.sum())
    assert max_px < 0.01 and max_m < 1e-3, (max_px, max_m)
    for instance in nusc.instance:
        token, count = instance["first_annotation_token"], 0
        while token:
            count += 1
            last = token
            token = nusc.get("sample_annotation", token)["next"]
        assert count == instance["nbr_annotations"] and last == instance["last_annotation_token"]
    print(f"devkit OK: {len(nusc.scene)} scenes, {n_samples} samples, {n_sd} get_sample_data calls, "
          f"{n_boxes} boxes (get_box + box_velocity), {n_boxes_in_cam} box centres inside camera images, "
          f"{n_compared} LiDAR points projected by the devkit and by ago (max difference {max_px:.4f} px, "
          f"{max_m:.6f} m depth); "
          f"{time.time() - t0:.2f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataroot", type=Path, required=True)
    parser.add_argument("--version", default="v1.0-mini")
    parser.add_argument("--write", action="store_true", help="write a small dataset at --dataroot first")
    args = parser.parse_args()
    if args.write:
        write_dataset(args.dataroot, args.version)
    check(args.dataroot, args.version)


if __name__ == "__main__":
    main()
