"""Read a dataset in the Occ3D-Waymo layout (what `ago synth --rig waymo|front` writes) as `Frame`s.

Takes a root holding `cam_infos.json` (our JSON stand-in for Occ3D-Waymo's `cam_infos.pkl`: the camera
names in image_<k> order, then per sample its split, scene, frame, timestamp, ego2global and each camera's
intrinsics, sensor2ego and image size), `splits.json` ({"train": ["training/000", ...], "val": [...]}),
the images `kitti_format/<split>/image_<k>/<sample>.jpg`, optionally the LiDAR
`kitti_format/<split>/velodyne/<sample>.bin`, the ground truth `<split>/<scene>/<frame>_04.npz` (under the
root or `gts_root`) and the synthetic per-pixel maps `synthetic/{semantic,depth}/<camera>/<sample>.png`.
docs/dataset_format.md, "Occ3D-Waymo", has the layout and its sources.

It offers what `NuScenesDataset` offers its users (`len`, `[i]`, `sample_tokens`, `scene_of`, `scenes`,
`split`, `split_note`, `indices_of`, `index_of`, `neighbours`, the non-key sweep queries), with:
- token = the sample name `<p><scene:03d><frame:03d>` (p = 0 training, 1 validation, 2 test), scene =
  `<split>/<scene:03d>` (the names splits.json lists); keyframes ordered by scene, then frame;
- `rig`: the cameras in cam_infos.json's order (Waymo: FRONT, FRONT_LEFT, FRONT_RIGHT, SIDE_LEFT,
  SIDE_RIGHT), each with its own image size;
- `sweeps[0]`: the velodyne points as (N, 5) float32 [x, y, z, intensity, elongation] in the ego frame
  (the file's frame), so lidar2ego is the identity; no earlier sweeps and no non-key sweeps (the layout
  lists none: `num_nonkey_lidar` = 0);
- `gt`: `Occ3DLabels` in the Occ3D-Waymo table's ids (free 23): semantics = `voxel_label`, mask_lidar =
  `origin_voxel_state`, mask_camera = `final_voxel_state & infov` (the mask Occ3D-Waymo's loaders train and
  score with: CVT-Occ's `LoadOccGTFromFileWaymo` with use_camera_mask and use_infov_mask); `class_table`
  (OCC3D_WAYMO) says which ids they are, so a label space must be one of that table (`@table: occ3d_waymo`).

Reading is bounded (read_json, the npz and point-file readers) and every problem is one AgoInputError
naming the file: a malformed cam_infos.json, a sample name that does not match its split/scene/frame, a
camera missing from a sample, a missing image, a file name leaving the root.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ago_runtime.classes import OCC3D_WAYMO, dataset_class_table
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.frame import Frame, LidarSweep
from ago_runtime.formats.nuscenes import default_split_positions, read_jpeg_rgb, read_lidar_bin
from ago_runtime.formats.nuscenes_schema import check_rigid
from ago_runtime.formats.occ3d_waymo import Occ3DWaymoLabels, gt_path, sample_of
from ago_runtime.formats.occ3d_waymo_writer import SPLIT_PREFIX, VELODYNE_COLUMNS, image_name, velodyne_name
from ago_runtime.formats.scenes import indices_of, neighbour_indices, scene_spans
from ago_runtime.formats.synthetic_maps import read_synthetic_maps
from ago_runtime.geometry.camera import MAX_CAMERAS, Camera, Rig
from ago_runtime.geometry.grid import Grid
from ago_runtime.paths import inside_root
from ago_runtime.readers import read_json

CAM_INFOS = "cam_infos.json"
_SAMPLE = re.compile(r"^[0-2]\d{6}$")
_SPLIT_OF_PREFIX = {v: k for k, v in SPLIT_PREFIX.items()}


def is_occ3d_waymo_root(root: str | Path) -> bool:
    """True when `root` holds the Occ3D-Waymo layout's cam_infos.json."""
    return (Path(root) / CAM_INFOS).is_file()


def _matrix(value, shape: tuple[int, int], where: Path, what: str) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape != shape or not np.all(np.isfinite(m)):
        raise AgoInputError(where, f"{what} must be a {shape[0]}x{shape[1]} matrix of finite numbers")
    return m


class Occ3DWaymoDataset:
    """Indexable keyframes of a dataset in the Occ3D-Waymo layout, ordered by split, scene, then frame."""

    class_table = OCC3D_WAYMO
    num_nonkey_lidar = 0          # the layout lists no non-key LiDAR sweeps

    def __init__(self, root: str | Path, gts_root: str | Path | None = None, load_images: bool = True,
                 load_extras: bool = True, num_sweeps: int = 0, grid: Grid | None = None,
                 allow_outside_root: bool = False):
        self.root = Path(root)
        self.class_table = dataset_class_table(self.root, OCC3D_WAYMO)   # the folder's class_table.json, if any
        if not self.root.is_dir():
            raise AgoInputError(self.root, "dataset folder not found")
        self.gts_root = Path(gts_root) if gts_root is not None else self.root
        self.load_images = load_images
        self.load_extras = load_extras
        if num_sweeps < 0:
            raise AgoInputError(None, f"num_sweeps must be >= 0, got {num_sweeps}")
        self.num_sweeps = int(num_sweeps)   # earlier sweeps: none in this layout (only the keyframe's is read)
        self.grid = grid
        self.allow_outside_root = allow_outside_root
        self.infos_path = self.root / CAM_INFOS
        self.table_dir = self.root   # where errors about the index point (NuScenesDataset's name for it)
        infos = read_json(self.infos_path, missing="no cam_infos.json (is this an Occ3D-Waymo layout root?)",
                          expect=dict)
        self.camera_names = self._camera_names(infos.get("cameras"))
        frames = infos.get("frames")
        if not isinstance(frames, dict) or not frames:
            raise AgoInputError(self.infos_path, "'frames' must be a non-empty object {sample name: frame info}")
        self._info: dict[str, dict] = {}
        order = []
        for sample, info in frames.items():
            split, scene, frame = self._check_sample(sample, info)
            self._info[sample] = info
            order.append((SPLIT_PREFIX[split], scene, frame, sample))
        order.sort()
        self.sample_tokens: list[str] = [s for *_, s in order]
        self._scene_names: list[str] = [f"{_SPLIT_OF_PREFIX[p]}/{scene:03d}" for p, scene, _, _ in order]
        self._index = {tok: i for i, tok in enumerate(self.sample_tokens)}
        self._scene_span = scene_spans(self._scene_names)

    # ------------------------------------------------------------------ cam_infos.json checks
    def _camera_names(self, names) -> list[str]:
        if (not isinstance(names, list) or not 1 <= len(names) <= MAX_CAMERAS
                or not all(isinstance(n, str) and re.fullmatch(r"[A-Za-z0-9_\-]{1,64}", n) for n in names)
                or len(set(names)) != len(names)):
            raise AgoInputError(self.infos_path, f"'cameras' must list 1..{MAX_CAMERAS} distinct camera names "
                                "(letters, digits, _ or -), in image_<k> order")
        return list(names)

    def _check_sample(self, sample, info) -> tuple[str, int, int]:
        where = self.infos_path
        if not isinstance(sample, str) or not _SAMPLE.match(sample):
            raise AgoInputError(where, f"sample name {str(sample)[:40]!r} is not <p><scene:03d><frame:03d> "
                                "(seven digits, p = 0 training, 1 validation, 2 test)")
        if not isinstance(info, dict):
            raise AgoInputError(where, f"sample {sample}: its info must be an object")
        split, scene, frame = info.get("split"), info.get("scene"), info.get("frame")
        if split not in SPLIT_PREFIX or not isinstance(scene, int) or not isinstance(frame, int) \
                or isinstance(scene, bool) or isinstance(frame, bool):
            raise AgoInputError(where, f"sample {sample}: needs 'split' (one of {', '.join(SPLIT_PREFIX)}) and "
                                "integer 'scene' and 'frame'")
        if not (0 <= scene <= 999 and 0 <= frame <= 999) or sample_of(split, scene, frame) != sample:
            raise AgoInputError(where, f"sample {sample}: its name does not match split {split!r}, scene {scene}, "
                                f"frame {frame} (expected {SPLIT_PREFIX[split]}{scene % 1000:03d}{frame % 1000:03d})")
        _matrix(info.get("ego2global"), (4, 4), where, f"sample {sample}: 'ego2global'")
        cams = info.get("cameras")
        if not isinstance(cams, dict):
            raise AgoInputError(where, f"sample {sample}: 'cameras' must be an object {{camera name: calibration}}")
        missing = [c for c in self.camera_names if c not in cams]
        if missing:
            raise AgoInputError(where, f"sample {sample}: no calibration for camera(s) {', '.join(missing)}")
        return split, scene, frame

    # ------------------------------------------------------------------ lookups (NuScenesDataset's interface)
    def __len__(self) -> int:
        return len(self.sample_tokens)

    def index_of(self, token: str) -> int:
        if token not in self._index:
            raise AgoInputError(self.infos_path, f"no sample {token!r}")
        return self._index[token]

    def indices_of(self, names: list[str]) -> list[int]:
        """Dataset indices of sample names and/or scene names (`training/000`: its keyframes in order), in the
        order given; every name that is neither is listed in one AgoInputError."""
        return indices_of(names, self._index, self._scene_names, self.infos_path, "sample or scene")

    def scene_of(self, i: int) -> str:
        return self._scene_names[i]

    def scenes(self) -> list[str]:
        return list(dict.fromkeys(self._scene_names))

    def split(self, name: str) -> list[int]:
        """Indices of the scenes splits.json lists under `name` ("all": every one). Without splits.json:
        "train" = the samples of training/, "val" = those of validation/ (the dataset's own folders)."""
        if name == "all":
            return list(range(len(self)))
        path = self.root / "splits.json"
        if not path.is_file() and name in ("train", "val"):
            folder = "training" if name == "train" else "validation"
            return [i for i, s in enumerate(self._scene_names) if s.startswith(folder + "/")]
        splits = read_json(path, missing=f"no splits.json, so no split {name!r}: use 'all', 'train' (training/) "
                           "or 'val' (validation/)")
        if not isinstance(splits, dict) or name not in splits:
            names = sorted(splits) if isinstance(splits, dict) else []
            raise AgoInputError(path, f"no split {name!r}; it has {names} (and 'all')")
        wanted = splits[name]
        if not isinstance(wanted, list) or not all(isinstance(s, str) for s in wanted):
            raise AgoInputError(path, f"split {name!r} must be a list of scene names like 'training/000'")
        unknown = sorted(set(wanted) - set(self._scene_names))
        if unknown:
            raise AgoInputError(path, f"split {name!r} names scenes not in {CAM_INFOS}: {unknown[:10]}")
        return [i for i, s in enumerate(self._scene_names) if s in set(wanted)]

    def split_note(self, name: str) -> str | None:
        if name not in ("train", "val") or (self.root / "splits.json").is_file():
            return None
        folder = "training" if name == "train" else "validation"
        return (f"split {name!r} = the samples of {folder}/ ({len(self.split(name))} of {len(self)}; "
                f"{self.root / 'splits.json'} not found)")

    def neighbours(self, i: int, count: int, interval: int) -> list[int]:
        """Up to `count` keyframe indices of i's scene at offsets +interval*k, -interval*k (k = 1, 2, ...),
        nearest first (+ before -); a side that reaches its scene end stops and the other goes on."""
        return neighbour_indices(self._scene_span[i], i, count, interval)

    def nonkey_sweeps(self, i: int, count: int | None = None) -> list[LidarSweep]:
        return []

    def max_nonkey_sweeps(self) -> int:
        return 0

    def nonkey_sweep_files_present(self) -> bool:
        return False

    # ------------------------------------------------------------------ files
    def _path(self, relative: str) -> Path:
        return inside_root(self.root, relative, self.infos_path, "file name", self.allow_outside_root)

    def image_file(self, i: int, camera: str) -> Path:
        info = self._info[self.sample_tokens[i]]
        k = self.camera_names.index(camera)
        return self._path(image_name(info["split"], k, self.sample_tokens[i]))

    def lidar_file(self, i: int) -> Path:
        info = self._info[self.sample_tokens[i]]
        return self._path(velodyne_name(info["split"], self.sample_tokens[i]))

    def lidar_pose(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(lidar2ego, ego2global) of sample i: the points are in the ego frame, so lidar2ego is the identity."""
        token = self.sample_tokens[i]
        return np.eye(4), _matrix(self._info[token]["ego2global"], (4, 4), self.infos_path, f"sample {token}: 'ego2global'")

    def gt_file(self, i: int) -> Path:
        info = self._info[self.sample_tokens[i]]
        return gt_path(self.gts_root, info["split"], info["scene"], info["frame"])

    def has_lidar(self) -> bool:
        """Whether the first sample's velodyne file exists (a camera-only copy of the layout has none)."""
        return len(self) > 0 and self.lidar_file(0).is_file()

    # ------------------------------------------------------------------ frames
    def __getitem__(self, i: int) -> Frame:
        if not -len(self) <= i < len(self):
            raise IndexError(i)
        i = i % len(self)
        token = self.sample_tokens[i]
        info = self._info[token]
        where = self.infos_path
        ego2global = _matrix(info["ego2global"], (4, 4), where, f"sample {token}: 'ego2global'")
        problem = check_rigid(ego2global)
        if problem:
            raise AgoInputError(where, f"sample {token}: ego2global {problem}")
        timestamp = info.get("timestamp", 0)
        if not isinstance(timestamp, int) or isinstance(timestamp, bool):
            raise AgoInputError(where, f"sample {token}: 'timestamp' must be an integer (microseconds)")
        cameras, images, paths, extras = [], {}, {}, {}
        for name in self.camera_names:
            cal = info["cameras"][name]
            if not isinstance(cal, dict):
                raise AgoInputError(where, f"sample {token}: camera {name} calibration must be an object")
            K = _matrix(cal.get("intrinsics"), (3, 3), where, f"sample {token} {name}: 'intrinsics'")
            cam2ego = _matrix(cal.get("sensor2ego"), (4, 4), where, f"sample {token} {name}: 'sensor2ego'")
            path = self.image_file(i, name)
            if not path.is_file():
                raise AgoInputError(path, f"image of sample {token} camera {name} is missing")
            paths[name] = str(path)
            if self.load_images:
                images[name] = read_jpeg_rgb(path)
                height, width = images[name].shape[:2]
            else:
                width, height = cal.get("width"), cal.get("height")
                if not (isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0):
                    height, width = read_jpeg_rgb(path).shape[:2]
            cameras.append(Camera(name, K, cam2ego, int(width), int(height)))
            if self.load_extras:
                read_synthetic_maps(self.root, extras, name, token, (int(height), int(width)))
        try:
            rig = Rig(cameras)
        except AgoInputError as e:
            raise AgoInputError(where, e.problem) from None
        rig.validate(str(where))

        sweeps = []
        lidar = self.lidar_file(i)
        if lidar.is_file():
            points = read_lidar_bin(lidar, len(VELODYNE_COLUMNS), ", ".join(VELODYNE_COLUMNS))
            sweeps.append(LidarSweep(np.ascontiguousarray(points[:, :5]), np.eye(4), ego2global, timestamp,
                                     str(lidar)))

        gt = None
        gt_file = self.gt_file(i)
        if gt_file.is_file():
            gt = Occ3DWaymoLabels.load(gt_file, self.grid.shape if self.grid is not None else None).as_occ3d()

        return Frame(token=token, scene=self._scene_names[i], timestamp=timestamp, rig=rig, ego2global=ego2global,
                     images=images, image_paths=paths, sweeps=sweeps, gt=gt, extras=extras)
