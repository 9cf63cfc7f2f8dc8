"""Write a dataset in the Occ3D-Waymo ground-truth layout (what `ago synth --rig waymo|front` produces).

Per keyframe: the ground truth `<split>/<scene:03d>/<frame:03d>_04.npz` exactly as Occ3D-Waymo ships it
(`formats.occ3d_waymo`), the camera images `kitti_format/<split>/image_<k>/<sample>.jpg` (k = camera index
in the rig's order, sample = `<p><scene:03d><frame:03d>` with p = 0 training, 1 validation, 2 test: the
mmdet3d KITTI-format naming Occ3D-Waymo loaders parse) and, at `close()`, `cam_infos.json` (our JSON
stand-in for the `cam_infos.pkl` pickles: per sample the ego pose and each camera's intrinsics,
sensor2ego and image size) and `splits.json`. docs/dataset_format.md, "Occ3D-Waymo", has the layout.
Every file goes through a temporary file + rename; the same inputs give byte-identical files.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ago_runtime.atomic import write_bytes, write_json
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.occ3d_waymo import Occ3DWaymoLabels, gt_path

JPEG_QUALITY = 95
SPLIT_PREFIX = {"training": 0, "validation": 1, "test": 2}


def sample_name(split: str, scene: int, frame: int) -> str:
    """`<p><scene:03d><frame:03d>`: characters 1..3 are the scene and 4..6 the frame, as Occ3D-Waymo loaders read them."""
    return f"{SPLIT_PREFIX[split]}{int(scene):03d}{int(frame):03d}"


class Occ3DWaymoWriter:
    def __init__(self, root: str | Path, camera_names: list[str] | tuple[str, ...]):
        self.root = Path(root)
        self.camera_names = tuple(camera_names)
        if not self.camera_names or len(set(self.camera_names)) != len(self.camera_names):
            raise AgoInputError(root, f"need distinct camera names, got {list(camera_names)}")
        self.frames: dict[str, dict] = {}

    def add_frame(self, split: str, scene: int, frame: int, ego2global: np.ndarray, cameras, images: dict,
                  gt: Occ3DWaymoLabels) -> str:
        """Write one keyframe (images RGB uint8 by camera name, cameras in the writer's order); returns the sample name."""
        names = tuple(c.name for c in cameras)
        if names != self.camera_names:
            raise AgoInputError(self.root, f"cameras {list(names)} differ from the writer's {list(self.camera_names)}")
        path = gt_path(self.root, split, scene, frame)
        sample = sample_name(split, scene, frame)
        gt.save(path)
        cams = {}
        for k, cam in enumerate(cameras):
            img = np.asarray(images[cam.name])
            if img.shape != (cam.height, cam.width, 3):
                raise AgoInputError(cam.name, f"image {img.shape} is not {cam.height}x{cam.width}x3")
            ok, jpg = cv2.imencode(".jpg", np.ascontiguousarray(img[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                raise AgoInputError(cam.name, "JPEG encoding failed")
            write_bytes(self.root / "kitti_format" / split / f"image_{k}" / f"{sample}.jpg", jpg.tobytes())
            cams[cam.name] = {"intrinsics": np.round(cam.intrinsics, 6).tolist(),
                              "sensor2ego": np.round(cam.cam2ego, 9).tolist(), "width": cam.width, "height": cam.height}
        self.frames[sample] = {"split": split, "scene": int(scene), "frame": int(frame),
                               "ego2global": np.round(np.asarray(ego2global, float), 9).tolist(), "cameras": cams}
        return sample

    def close(self, splits: dict[str, list[str]]) -> None:
        write_json(self.root / "cam_infos.json", {"cameras": list(self.camera_names),
                                                  "frames": dict(sorted(self.frames.items()))})
        write_json(self.root / "splits.json", splits)
