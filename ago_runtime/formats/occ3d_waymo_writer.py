"""Write a dataset in the Occ3D-Waymo ground-truth layout (what `ago synth --rig waymo|front` produces).

Per keyframe: the ground truth `<split>/<scene:03d>/<frame:03d>_04.npz` exactly as Occ3D-Waymo ships it
(`formats.occ3d_waymo`), the camera images `kitti_format/<split>/image_<k>/<sample>.jpg` (k = camera index
in the rig's order, sample = `<p><scene:03d><frame:03d>` with p = 0 training, 1 validation, 2 test: the
mmdet3d KITTI-format naming Occ3D-Waymo loaders parse) and, at `close()`, `cam_infos.json` (our JSON
stand-in for the `cam_infos.pkl` pickles: per sample the ego pose and each camera's intrinsics,
sensor2ego and image size) and `splits.json`. With LiDAR: `kitti_format/<split>/velodyne/<sample>.bin`, float32 N x 6
[x, y, z, intensity, elongation, timestamp] in the vehicle (ego) frame, as mmdetection3d's Waymo converter writes
it (`VELODYNE_COLUMNS`). With per-pixel extras: `synthetic/{semantic,depth}/<camera>/<sample>.png`
(`formats.synthetic_maps`, ours). docs/dataset_format.md, "Occ3D-Waymo", has the layout.
Every file goes through a temporary file + rename; the same inputs give byte-identical files.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ago_runtime.atomic import write_bytes, write_json
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.occ3d_waymo import SPLITS, Occ3DWaymoLabels, gt_path, sample_of
from ago_runtime.formats.synthetic_maps import write_synthetic_maps
from ago_runtime.formats.nuscenes_schema import check_rigid

JPEG_QUALITY = 95
SPLIT_PREFIX = {split: p for p, split in enumerate(SPLITS)}   # training 0, validation 1, test 2
VELODYNE_COLUMNS = ("x", "y", "z", "intensity", "elongation", "timestamp")   # float32, vehicle frame


def velodyne_name(split: str, sample: str) -> str:
    """`kitti_format/<split>/velodyne/<sample>.bin` under the root (mmdetection3d's KITTI-format Waymo folders)."""
    return f"kitti_format/{split}/velodyne/{sample}.bin"


def image_name(split: str, camera_index: int, sample: str) -> str:
    """`kitti_format/<split>/image_<k>/<sample>.jpg` under the root (k: the camera's index in cam_infos.json)."""
    return f"kitti_format/{split}/image_{camera_index}/{sample}.jpg"


def velodyne_points(lidar_points: np.ndarray, lidar2ego: np.ndarray, timestamp_us: int) -> np.ndarray:
    """(N, >= 4) points [x, y, z, intensity, ...] in a LiDAR frame -> (N, 6) float32 velodyne rows in the ego
    frame: x, y, z moved by lidar2ego, the intensity, elongation 0 (a synthetic LiDAR has none), the timestamp
    in microseconds (float32, as mmdetection3d 0.x writes `frame.timestamp_micros`)."""
    p = np.asarray(lidar_points, np.float64)
    if p.ndim != 2 or p.shape[1] < 4:
        raise AgoInputError(None, f"lidar_points must be (N, >= 4) [x, y, z, intensity, ...], got {p.shape}")
    m = np.asarray(lidar2ego, np.float64)
    out = np.zeros((len(p), len(VELODYNE_COLUMNS)), np.float32)
    out[:, :3] = p[:, :3] @ m[:3, :3].T + m[:3, 3]
    out[:, 3] = p[:, 3]
    out[:, 5] = float(timestamp_us)
    return out


class Occ3DWaymoWriter:
    def __init__(self, root: str | Path, camera_names: list[str] | tuple[str, ...]):
        self.root = Path(root)
        self.camera_names = tuple(camera_names)
        if not self.camera_names or len(set(self.camera_names)) != len(self.camera_names):
            raise AgoInputError(root, f"need distinct camera names, got {list(camera_names)}")
        self.frames: dict[str, dict] = {}

    def add_frame(self, split: str, scene: int, frame: int, ego2global: np.ndarray, cameras, images: dict,
                  gt: Occ3DWaymoLabels, timestamp_us: int = 0, lidar_points: np.ndarray | None = None,
                  lidar2ego: np.ndarray | None = None, extras: dict | None = None) -> str:
        """Write one keyframe (images RGB uint8 by camera name, cameras in the writer's order); returns the sample name.

        lidar_points: (N, 5) float32 in the LiDAR frame with its `lidar2ego` (written in the ego frame);
        extras: {"semantic": {cam: (H, W) uint8}, "depth": {cam: (H, W) float32 m}} (synthetic/ maps)."""
        names = tuple(c.name for c in cameras)
        if names != self.camera_names:
            raise AgoInputError(self.root, f"cameras {list(names)} differ from the writer's {list(self.camera_names)}")
        for what, m in (("ego2global", ego2global), ("lidar2ego", lidar2ego)):
            problem = None if m is None else check_rigid(np.asarray(m, float))
            if problem:
                raise AgoInputError(self.root, f"{split}/{scene:03d}/{frame:03d}: {what} {problem}")
        if (lidar_points is None) != (lidar2ego is None):
            raise AgoInputError(self.root, "give lidar_points and lidar2ego together")
        path = gt_path(self.root, split, scene, frame)
        sample = sample_of(split, scene, frame)
        gt.save(path)
        if lidar_points is not None:
            write_bytes(self.root / velodyne_name(split, sample),
                        velodyne_points(lidar_points, lidar2ego, timestamp_us).tobytes())
        cams = {}
        for k, cam in enumerate(cameras):
            img = np.asarray(images[cam.name])
            if img.shape != (cam.height, cam.width, 3):
                raise AgoInputError(cam.name, f"image {img.shape} is not {cam.height}x{cam.width}x3")
            bgr = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2BGR)
            ok, jpg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                raise AgoInputError(cam.name, "JPEG encoding failed")
            write_bytes(self.root / image_name(split, k, sample), jpg.tobytes())
            if extras:
                write_synthetic_maps(self.root, extras, cam.name, sample, (cam.height, cam.width))
            cams[cam.name] = {"intrinsics": np.round(cam.intrinsics, 6).tolist(),
                              "sensor2ego": np.round(cam.cam2ego, 9).tolist(), "width": cam.width, "height": cam.height}
        self.frames[sample] = {"split": split, "scene": int(scene), "frame": int(frame), "timestamp": int(timestamp_us),
                               "ego2global": np.round(np.asarray(ego2global, float), 9).tolist(), "cameras": cams}
        return sample

    def close(self, splits: dict[str, list[str]]) -> None:
        write_json(self.root / "cam_infos.json", {"cameras": list(self.camera_names),
                                                  "frames": dict(sorted(self.frames.items()))})
        write_json(self.root / "splits.json", splits)
