"""Read a nuScenes-format dataset (real nuScenes or one written by `NuScenesWriter`) as `Frame`s.

Takes a dataset root holding `<version>/*.json` (of nuScenes' thirteen tables the six it reads: sensor,
calibrated_sensor, ego_pose, scene, sample, sample_data; all missing ones are named at once), `samples/`
(and `sweeps/` for non-key LiDAR sweeps: `nonkey_sweeps(i)`), optionally `gts/<scene>/<sample token>/labels.npz` (Occ3D GT,
or any `gts_root`), `synthetic/{semantic,depth}/<CAM>/<image stem>.png` (what `ago synth` writes)
and `splits.json`.

Gives, per keyframe (sample), a `Frame`:
- `images[cam]`: (H, W, 3) uint8 RGB for the camera channels of the sensor table (nuScenes' six in
  CAMERA_NAMES order, then any others in the table's order: the rig), with their paths;
- `rig`: intrinsics and cam2ego from each camera's calibrated_sensor; width/height from the image
  (from sample_data when images are not loaded);
- `ego2global`: the ego pose of the keyframe's LIDAR_TOP sample_data (4x4, metres);
- `sweeps[0]`: the keyframe LiDAR sweep ((N, 5) float32 in the LiDAR frame, lidar2ego, its own
  ego2global, timestamp in microseconds, path), then up to `num_sweeps` earlier LiDAR sweeps found by
  following sample_data `prev` links (whatever their is_key_frame, as mmdetection3d does), nearest first;
- `gt`: Occ3DLabels when `<gts_root>/<scene>/<token>/labels.npz` exists;
- `extras["semantic"][cam]`: (H, W) uint8 Occ3D ids (255 none) and `extras["depth"][cam]`: (H, W)
  float32 metres (0 none), when the synthetic/ PNGs exist and `load_extras`.

Camera poses: in real nuScenes every camera image has its own timestamp and ego pose (the cameras
fire up to ~50 ms before/after the LiDAR sweep while the car moves). A `Frame` carries ONE ego pose,
the keyframe LiDAR's, so each camera's cam2ego is expressed in THAT ego frame:
- `compensate_ego_motion=True` (default): cam2ego = inv(ego2global_lidar) @ ego2global_camera @
  cam2ego_calibrated, i.e. the camera where it really was when its image was taken, seen from the
  keyframe's ego frame (what mmdetection3d's `lidar2cam` holds; on the real keyframe in ../shared this
  moves CAM_FRONT by 0.33 m at ~9 m/s);
- `compensate_ego_motion=False`: the calibrated_sensor cam2ego as is (the ego motion between the LiDAR
  and the camera exposures is ignored).
Datasets written by `NuScenesWriter` are exactly synchronised, so both give the same rig there.

Non-key LiDAR sweeps (`is_key_frame` false in sample_data.json): `nonkey_sweeps(i, count)` gives those
recorded just before keyframe i (its prev chain back to the previous keyframe, nearest first), each with
its own ego pose; `ago pseudo-labels --sweeps` uses them. `num_nonkey_lidar` counts them.

Bad input raises AgoInputError naming the file: a missing table, a record pointing at a missing file or
token, a sample without one of the six cameras or LIDAR_TOP, an undecodable or truncated JPEG, a LiDAR
file whose size is not a multiple of 20 bytes, a labels.npz with the wrong shape.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ago_runtime.classes import OCC3D_NUSCENES, dataset_class_table
from ago_runtime.geometry.camera import CAMERA_NAMES, Camera, Rig
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.image_files import decode_image
from ago_runtime.readers import max_array_bytes, read_json
from ago_runtime.formats.frame import Frame, LidarSweep
from ago_runtime.geometry.grid import Grid
from ago_runtime.formats.nuscenes_schema import LIDAR_CHANNEL, check_table, record_to_matrix
from ago_runtime.paths import inside_root
from ago_runtime.formats.occ3d import Occ3DLabels, labels_path
from ago_runtime.formats.scenes import indices_of, neighbour_indices, scene_spans
from ago_runtime.formats.synthetic_maps import read_synthetic_maps

# The tables the reader needs (the other seven of nuScenes' thirteen may be absent).
READ_TABLES = ("sensor", "calibrated_sensor", "ego_pose", "scene", "sample", "sample_data")
# Without splits.json: this fraction of each scene's first keyframes is "train", the rest "val".
DEFAULT_TRAIN_SHARE = (3, 4)


def default_split_positions(n: int, name: str) -> range:
    """Without splits.json: the positions (in time order) of a scene of n keyframes in split "train" (the
    first n * 3 // 4) or "val" (the rest)."""
    cut = n * DEFAULT_TRAIN_SHARE[0] // DEFAULT_TRAIN_SHARE[1]
    return range(0, cut) if name == "train" else range(cut, n)


# ---------------------------------------------------------------------------- file readers
def read_jpeg_rgb(path: str | Path) -> np.ndarray:
    """A JPEG file -> (H, W, 3) uint8 RGB; refuses missing, non-JPEG, truncated or undecodable files."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise AgoInputError(path, "image file not found") from None
    except OSError as e:
        raise AgoInputError(path, f"cannot read the image ({e})") from None
    if len(data) < 4 or data[:2] != b"\xff\xd8":
        raise AgoInputError(path, "not a JPEG file (no start-of-image marker)")
    if not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        raise AgoInputError(path, "truncated JPEG (no end-of-image marker FFD9)")
    bgr = decode_image(data, path, cv2.IMREAD_COLOR)
    if bgr.ndim != 3 or bgr.shape[2] != 3:
        raise AgoInputError(path, "corrupt JPEG (cv2 cannot decode it)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)   # (far faster than copying a reversed-axis view)


def read_lidar_bin(path: str | Path, columns: int = 5, fields: str = "x, y, z, intensity, ring") -> np.ndarray:
    """A float32 point file of `columns` values per point (nuScenes' .pcd.bin: 5; the Occ3D-Waymo KITTI-format
    velodyne .bin: 6) -> (N, columns) float32; refuses sizes not a multiple of a point's bytes."""
    path = Path(path)
    if not path.is_file():
        raise AgoInputError(path, "LiDAR file not found")
    size = path.stat().st_size
    if size > max_array_bytes():   # a real sweep is ~2 MB; refused by size before a byte is read
        raise AgoInputError(path, f"LiDAR file of {size} bytes, more than ago reads ({max_array_bytes()}; "
                                  "$AGO_MAX_ARRAY_BYTES sets the limit)")
    point_bytes = 4 * columns
    if size % point_bytes:
        raise AgoInputError(path, f"size {size} bytes is not a multiple of {point_bytes} "
                                  f"(float32 {fields} per point)")
    points = np.fromfile(path, dtype=np.float32).reshape(-1, columns)
    if not np.all(np.isfinite(points[:, :3])):
        raise AgoInputError(path, "LiDAR points contain NaN or inf")
    return points


def load_table(table_dir: Path, name: str) -> list[dict]:
    path = Path(table_dir) / f"{name}.json"
    table = read_json(path, missing="missing nuScenes table")   # bounded size and nesting
    if not isinstance(table, list) or not all(isinstance(r, dict) and isinstance(r.get("token"), str)
                                              for r in table):
        raise AgoInputError(path, "a nuScenes table must be a JSON list of records with a 'token' string")
    check_table(name, table, path)   # the field types the reader relies on (nuscenes_schema)
    return table


def find_version(root: Path) -> str:
    """The single `v1.0-*` table folder under `root`."""
    found = sorted(p.name for p in Path(root).glob("v1.0-*") if p.is_dir())
    if not found:
        raise AgoInputError(root, "no v1.0-* table folder (is this a nuScenes dataset root?)")
    if len(found) > 1:
        raise AgoInputError(root, f"several table folders {found}; pass the version")
    return found[0]


# ---------------------------------------------------------------------------- the dataset
class NuScenesDataset:
    """Indexable keyframes of a nuScenes-format dataset, ordered by scene name, then timestamp."""

    class_table = OCC3D_NUSCENES   # the layout's ids of ground truth and synthetic maps; a folder's class_table.json overrides it

    def __init__(self, root: str | Path, version: str | None = None, gts_root: str | Path | None = None,
                 load_images: bool = True, load_extras: bool = True, num_sweeps: int = 0,
                 grid: Grid | None = None, compensate_ego_motion: bool = True, allow_outside_root: bool = False):
        self.root = Path(root)
        self.class_table = dataset_class_table(self.root, OCC3D_NUSCENES)   # the folder's class_table.json, if any
        self.allow_outside_root = allow_outside_root   # file names leaving the root (ago_runtime.paths)
        if not self.root.is_dir():
            raise AgoInputError(self.root, "dataset folder not found")
        self.version = version or find_version(self.root)
        self.table_dir = self.root / self.version
        if not self.table_dir.is_dir():
            raise AgoInputError(self.table_dir, "table folder not found")
        if gts_root is None:
            gts_root = self.root / "gts" if (self.root / "gts").is_dir() else None
        self.gts_root = Path(gts_root) if gts_root is not None else None
        self.load_images = load_images
        self.load_extras = load_extras
        if num_sweeps < 0:
            raise AgoInputError(None, f"num_sweeps must be >= 0, got {num_sweeps}")
        self.num_sweeps = int(num_sweeps)
        self.grid = grid
        self.compensate_ego_motion = compensate_ego_motion

        # A nuScenes release has thirteen tables; only the six read here are required (a trimmed
        # extract without attribute/log/map/visibility/... is fine). Every missing one is named at once.
        missing = [name for name in READ_TABLES if not (self.table_dir / f"{name}.json").is_file()]
        if len(missing) == 1:
            raise AgoInputError(self.table_dir / f"{missing[0]}.json", "missing nuScenes table (ago reads "
                                f"{', '.join(READ_TABLES)})")
        if missing:
            raise AgoInputError(self.table_dir, f"missing nuScenes tables {', '.join(f'{m}.json' for m in missing)} "
                                f"(ago reads {', '.join(READ_TABLES)})")
        t = {name: {r["token"]: r for r in load_table(self.table_dir, name)} for name in READ_TABLES}
        if not allow_outside_root:   # every file name stays under the root (ago_runtime.paths), checked before work
            for rec in t["sample_data"].values():
                inside_root(self.root, rec["filename"], self.table_dir / "sample_data.json", "file name")
        try:
            self._build_index(t)
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, AgoInputError):
                raise
            raise AgoInputError(self.table_dir, f"a table record lacks a field or has a wrong type "
                                                f"({e.__class__.__name__}: {e})") from None

    def _build_index(self, t: dict[str, dict[str, dict]]) -> None:
        self._calibrated = t["calibrated_sensor"]
        self._ego_pose = t["ego_pose"]
        self._sample_data = t["sample_data"]
        self._samples = t["sample"]

        # channel of every calibrated sensor, keyframe sample_data per (sample, channel)
        channel_of_calib = {}
        camera_channels = []   # in the sensor table's order
        for token, rec in self._calibrated.items():
            sensor = self._ref("sensor", t["sensor"], rec.get("sensor_token"), "calibrated_sensor")
            channel_of_calib[token] = sensor["channel"]
        for sensor in t["sensor"].values():
            if sensor.get("modality") == "camera" and sensor.get("channel") not in camera_channels:
                camera_channels.append(sensor.get("channel"))
        # the rig: the camera channels of the sensor table (nuScenes' six in CAMERA_NAMES order, then others)
        self.camera_names: list[str] = ([c for c in CAMERA_NAMES if c in camera_channels]
                                        + [c for c in camera_channels if c not in CAMERA_NAMES])
        if not self.camera_names:
            raise AgoInputError(self.table_dir / "sensor.json", "no camera sensor (modality 'camera')")
        self._key_data: dict[str, dict[str, dict]] = {}
        self.num_nonkey_lidar = 0   # non-key LIDAR_TOP sweeps listed in sample_data.json
        for rec in self._sample_data.values():
            if not rec.get("is_key_frame"):
                if channel_of_calib.get(rec.get("calibrated_sensor_token")) == LIDAR_CHANNEL:
                    self.num_nonkey_lidar += 1
                continue
            channel = channel_of_calib.get(rec.get("calibrated_sensor_token"))
            if channel is None:
                raise AgoInputError(self.table_dir / "sample_data.json",
                                    f"sample_data {rec['token']} points at an unknown calibrated_sensor")
            self._key_data.setdefault(rec["sample_token"], {})[channel] = rec

        scene_name = {tok: rec["name"] for tok, rec in t["scene"].items()}
        order = []
        for rec in self._samples.values():
            scene = scene_name.get(rec.get("scene_token"))
            if scene is None:
                raise AgoInputError(self.table_dir / "sample.json",
                                    f"sample {rec['token']} points at an unknown scene {rec.get('scene_token')!r}")
            have = self._key_data.get(rec["token"], {})
            for channel in (*self.camera_names, LIDAR_CHANNEL):
                if channel not in have:
                    raise AgoInputError(self.table_dir / "sample_data.json",
                                        f"sample {rec['token']} ({scene}) has no keyframe {channel}")
            order.append((scene, int(rec["timestamp"]), rec["token"]))
        order.sort()
        self.sample_tokens: list[str] = [tok for _, _, tok in order]
        self._scene_names: list[str] = [scene for scene, _, _ in order]
        self._index = {tok: i for i, tok in enumerate(self.sample_tokens)}
        self._scene_span = scene_spans(self._scene_names)   # [start, end) of each index's scene

    # ------------------------------------------------------------------ lookups
    def _ref(self, table: str, records: dict, token, referrer: str) -> dict:
        rec = records.get(token)
        if rec is None:
            raise AgoInputError(self.table_dir / f"{referrer}.json",
                                f"token {token!r} not found in {table}.json")
        return rec

    def __len__(self) -> int:
        return len(self.sample_tokens)

    def index_of(self, token: str) -> int:
        if token not in self._index:
            raise AgoInputError(self.table_dir / "sample.json", f"no sample with token {token!r}")
        return self._index[token]

    def indices_of(self, names: list[str]) -> list[int]:
        """Dataset indices of sample tokens and/or scene names (a scene: its keyframes in time order), in the
        order given; every name that is neither is listed in one AgoInputError."""
        return indices_of(names, self._index, self._scene_names, self.table_dir / "sample.json",
                          "sample token or scene name")

    def scene_of(self, i: int) -> str:
        return self._scene_names[i]

    def scenes(self) -> list[str]:
        """Scene names in dataset order."""
        return list(dict.fromkeys(self._scene_names))

    def split(self, name: str) -> list[int]:
        """Indices of the samples of the scenes listed under `name` in root/splits.json ("all": every one).

        Without splits.json (real nuScenes has none), "train" is the first 3/4 of each scene's keyframes
        (rounded down) and "val" the rest (`split_note` says so); any other name is refused, naming the fix."""
        if name == "all":
            return list(range(len(self)))
        path = self.root / "splits.json"
        if not path.is_file() and name in ("train", "val"):
            return self._default_split(name)
        splits = read_json(path, missing=f"no splits.json, so no split {name!r}: use 'all', 'train' or 'val' (without "
                           "splits.json: the first 3/4 / last 1/4 of each scene's keyframes), or write splits.json "
                           '{"train": [scene names], "val": [...]} (docs/dataset_format.md)')
        if not isinstance(splits, dict) or name not in splits:
            names = sorted(splits) if isinstance(splits, dict) else []
            raise AgoInputError(path, f"no split {name!r}; it has {names} (and 'all')")
        wanted = set(splits[name])
        unknown = sorted(wanted - set(self._scene_names))
        if unknown:
            raise AgoInputError(path, f"split {name!r} names scenes not in the dataset: {unknown[:10]}")
        return [i for i, s in enumerate(self._scene_names) if s in wanted]

    def _default_split(self, name: str) -> list[int]:
        """No splits.json: per scene, keyframes [0, n * 3 // 4) are "train", the rest "val"."""
        out = []
        for start, end in dict.fromkeys(self._scene_span):
            out += [start + k for k in default_split_positions(end - start, name)]
        return out

    def split_note(self, name: str) -> str | None:
        """What a split defaults to when splits.json is absent (None when it is read from the file or is 'all')."""
        if name not in ("train", "val") or (self.root / "splits.json").is_file():
            return None
        part = "first 3/4" if name == "train" else "last 1/4"
        return (f"split {name!r} = the {part} of each scene's keyframes ({len(self.split(name))} of {len(self)}; "
                f"{self.root / 'splits.json'} not found)")

    def neighbours(self, i: int, count: int, interval: int) -> list[int]:
        """Up to `count` keyframe indices of i's scene at offsets +interval*k, -interval*k (k = 1, 2, ...),
        nearest first (+ before -); a side that reaches its scene end stops and the other goes on."""
        return neighbour_indices(self._scene_span[i], i, count, interval)

    # ------------------------------------------------------------------ non-key LiDAR sweeps
    def nonkey_sweep_records(self, i: int, count: int | None = None) -> list[dict]:
        """sample_data records of the non-key LIDAR_TOP sweeps recorded just before keyframe i, nearest
        first: its `prev` chain up to (not including) the previous keyframe, at most `count` (None: all).
        Real nuScenes has ~9 between two keyframes (LiDAR 20 Hz, keyframes 2 Hz)."""
        record = self._key_data[self.sample_tokens[i]][LIDAR_CHANNEL]
        out: list[dict] = []
        while record.get("prev") and (count is None or len(out) < count):
            record = self._ref("sample_data", self._sample_data, record["prev"], "sample_data")
            if record.get("is_key_frame"):
                break
            out.append(record)
        return out

    def nonkey_sweeps(self, i: int, count: int | None = None) -> list[LidarSweep]:
        """The non-key LiDAR sweeps of `nonkey_sweep_records(i, count)`, read (points, lidar2ego, own ego pose)."""
        try:
            return [self._sweep(r) for r in self.nonkey_sweep_records(i, count)]
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, AgoInputError):
                raise
            raise AgoInputError(self.table_dir / "sample_data.json", f"a non-key sweep record of sample "
                                f"{self.sample_tokens[i]} lacks a field ({e.__class__.__name__}: {e})") from None

    def max_nonkey_sweeps(self) -> int:
        """The most non-key LiDAR sweeps found between two keyframes (0 when sample_data lists none)."""
        if not self.num_nonkey_lidar:
            return 0
        return max(len(self.nonkey_sweep_records(i)) for i in range(len(self)))

    def lidar_pose(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(lidar2ego, ego2global) of keyframe i's LIDAR_TOP sweep, from the tables (no file is read)."""
        record = self._key_data[self.sample_tokens[i]][LIDAR_CHANNEL]
        calib = self._ref("calibrated_sensor", self._calibrated, record["calibrated_sensor_token"], "sample_data")
        pose = self._ref("ego_pose", self._ego_pose, record["ego_pose_token"], "sample_data")
        return record_to_matrix(calib), record_to_matrix(pose)

    def gt_file(self, i: int) -> Path | None:
        """Where keyframe i's Occ3D labels.npz is (whether or not it exists); None without a GT folder."""
        if self.gts_root is None:
            return None
        return labels_path(self.gts_root, self._scene_names[i], self.sample_tokens[i])

    def has_lidar(self) -> bool:
        """Every keyframe lists a LIDAR_TOP file (checked when the tables are read)."""
        return True

    def nonkey_sweep_files_present(self) -> bool:
        """Whether the files of the listed non-key sweeps exist (a keyframes-only download lacks sweeps/)."""
        for i in range(len(self)):
            recs = self.nonkey_sweep_records(i, 1)
            if recs:
                return self._file_path(recs[0]).is_file()
        return False

    # ------------------------------------------------------------------ frames
    def _file_path(self, record: dict) -> Path:
        return inside_root(self.root, record["filename"], self.table_dir / "sample_data.json", "file name",
                           self.allow_outside_root)

    def _file(self, record: dict) -> Path:
        path = self._file_path(record)
        if not path.is_file():
            raise AgoInputError(path, f"file listed in sample_data.json (token {record['token']}) is missing")
        return path

    def _sweep(self, record: dict) -> LidarSweep:
        calib = self._ref("calibrated_sensor", self._calibrated, record["calibrated_sensor_token"], "sample_data")
        pose = self._ref("ego_pose", self._ego_pose, record["ego_pose_token"], "sample_data")
        path = self._file(record)
        return LidarSweep(read_lidar_bin(path), record_to_matrix(calib), record_to_matrix(pose),
                          int(record["timestamp"]), str(path))

    def __getitem__(self, i: int) -> Frame:
        if not -len(self) <= i < len(self):
            raise IndexError(i)
        i = i % len(self)
        try:
            return self._frame(i)
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, AgoInputError):
                raise
            raise AgoInputError(self.table_dir, f"sample {self.sample_tokens[i]}: a table record lacks a field "
                                                f"or has a wrong type ({e.__class__.__name__}: {e})") from None

    def _frame(self, i: int) -> Frame:
        token = self.sample_tokens[i]
        sample = self._samples[token]
        scene = self._scene_names[i]
        data = self._key_data[token]

        sweeps = [self._sweep(data[LIDAR_CHANNEL])]
        record = data[LIDAR_CHANNEL]
        while len(sweeps) <= self.num_sweeps and record.get("prev"):
            record = self._ref("sample_data", self._sample_data, record["prev"], "sample_data")
            sweeps.append(self._sweep(record))

        cameras, images, paths = [], {}, {}
        extras: dict = {}
        for cam in self.camera_names:
            rec = data[cam]
            calib = self._ref("calibrated_sensor", self._calibrated, rec["calibrated_sensor_token"], "sample_data")
            intrinsic = np.asarray(calib.get("camera_intrinsic") or [], dtype=np.float64)
            if intrinsic.shape != (3, 3):
                raise AgoInputError(self.table_dir / "calibrated_sensor.json",
                                    f"{cam} calibrated_sensor {calib['token']} has no 3x3 camera_intrinsic")
            path = self._file(rec)
            paths[cam] = str(path)
            if self.load_images:
                images[cam] = read_jpeg_rgb(path)
                height, width = images[cam].shape[:2]
            else:
                height, width = int(rec.get("height") or 0), int(rec.get("width") or 0)
                if width <= 0 or height <= 0:
                    height, width = read_jpeg_rgb(path).shape[:2]
            cam2ego = record_to_matrix(calib)
            if self.compensate_ego_motion:
                cam_pose = self._ref("ego_pose", self._ego_pose, rec["ego_pose_token"], "sample_data")
                cam2ego = np.linalg.inv(sweeps[0].ego2global) @ record_to_matrix(cam_pose) @ cam2ego
            cameras.append(Camera(cam, intrinsic, cam2ego, width, height))
            if self.load_extras:
                self._read_extras(extras, cam, path, (height, width))
        try:
            rig = Rig(cameras)
        except AgoInputError as e:
            raise AgoInputError(self.table_dir / "sensor.json", e.problem) from None
        rig.validate(str(self.table_dir / "calibrated_sensor.json"))

        gt = None
        if self.gts_root is not None:
            gt_path = labels_path(self.gts_root, scene, token)
            if gt_path.is_file():
                gt = Occ3DLabels.load(gt_path, self.grid.shape if self.grid is not None else None)

        return Frame(token=token, scene=scene, timestamp=int(sample["timestamp"]), rig=rig,
                     ego2global=sweeps[0].ego2global, images=images, image_paths=paths, sweeps=sweeps,
                     gt=gt, extras=extras)

    def _read_extras(self, extras: dict, cam: str, image_path: Path, hw: tuple[int, int]) -> None:
        read_synthetic_maps(self.root, extras, cam, image_path.stem, hw)
