"""Read mmdetection3d nuScenes info files (info format 1.1) WITHOUT trusting the pickle, as `Frame`s.

An info .pkl is {"metainfo": {...}, "data_list": [sample, ...]}; per sample:
- `token`, `timestamp` (seconds, float), `ego2global` (4x4, the LiDAR keyframe's ego pose);
- `images[CAM]`: `img_path` (file name under `<data_root>/samples/<CAM>/`, or a path relative to
  data_root), `cam2img` (3x3 or 4x4 intrinsics), `cam2ego` (4x4), `lidar2cam`, `timestamp`;
- `lidar_points`: `lidar_path` (under `samples/LIDAR_TOP/`), `lidar2ego` (4x4), `num_pts_feats` (5);
- `instances` (3D boxes in the LiDAR frame), which ago does not use.

Camera poses: `lidar2cam` in these files includes the ego motion between the LiDAR sweep and the
camera exposure (lidar -> ego at LiDAR time -> global -> ego at camera time -> camera). With
`compensate_ego_motion=True` (default) a camera's cam2ego is taken as lidar2ego @ inv(lidar2cam), i.e.
the camera seen from the keyframe (LiDAR) ego frame, the frame the Occ3D grid lives in; with False (or
when lidar2cam is absent) the calibrated `cam2ego` as is. See `ago_runtime.formats.nuscenes` for the same choice.

`SafeInfoUnpickler` only lets the pickle build plain containers and numpy scalars/arrays/dtypes (the
classes such files contain); any other global (os.system, builtins.eval, a custom class...) raises
AgoInputError before it is called. What a small file can make the reader allocate is bounded: files
over 2 GiB are refused unread (MAX_INFO_BYTES); `bytes(n)` / `bytearray(n)` from a number n over 1 MiB
and list/tuple/set/dict of anything but a container built from the file's own bytes are refused (a
30-byte pickle calling bytearray(3e9) would otherwise take 3 GB); numpy arrays must carry their data
(numpy checks the length); the plain copy (`to_plain`) stops past 8 values per byte of the file
(a list referenced from many places is not expanded without end). `convert_mmdet3d_info_to_json` turns an info .pkl into plain JSON
once; `load_info_json` reads that JSON; `load_mmdet3d_info` reads the .pkl directly. Both give the
same frames: scene = info's `scene_token` when present, else "" (format 1.1 has no scene name).
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path

import numpy as np

from ago_runtime.atomic import write_json
from ago_runtime.geometry.camera import CAMERA_NAMES, Camera, Rig
from ago_runtime.errors import AgoInputError
from ago_runtime.readers import read_json
from ago_runtime.formats.frame import Frame, LidarSweep
from ago_runtime.formats.nuscenes import read_jpeg_rgb, read_lidar_bin
from ago_runtime.formats.nuscenes_schema import check_rigid
from ago_runtime.paths import inside_root

# (module, name) pairs a mmdetection3d info pickle may reference; nothing else is ever imported.
_NUMPY_GLOBALS = {
    ("numpy", "dtype"): lambda: np.dtype,
    ("numpy", "ndarray"): lambda: np.ndarray,
    ("numpy.core.multiarray", "scalar"): lambda: _np_core("multiarray").scalar,
    ("numpy._core.multiarray", "scalar"): lambda: _np_core("multiarray").scalar,
    ("numpy.core.multiarray", "_reconstruct"): lambda: _np_core("multiarray")._reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): lambda: _np_core("multiarray")._reconstruct,
    ("numpy.core.numeric", "_frombuffer"): lambda: _np_core("numeric")._frombuffer,
    ("numpy._core.numeric", "_frombuffer"): lambda: _np_core("numeric")._frombuffer,
}
_BUILTINS = {"list", "dict", "tuple", "set", "frozenset", "int", "float", "complex", "bool", "str",
             "bytes", "bytearray", "slice"}
# Bounds on what a small file may make the reader allocate (module docstring).
MAX_INFO_BYTES = 2 << 30          # an info .pkl larger than 2 GiB is refused ($AGO_MAX_INFO_BYTES)
MAX_SIZED_ALLOC = 1 << 20         # bytes(n) / bytearray(n) from an integer n: at most 1 MiB
PLAIN_NODES_PER_BYTE = 8          # to_plain may make at most this many values per byte of the file (+ 200 000)
MAX_INFO_DEPTH = 32               # containers nested deeper than this are refused (an info file nests ~5 deep)


def _np_core(submodule: str):
    """numpy's core submodule under its numpy-2 name (numpy._core), falling back to numpy.core."""
    import importlib

    try:
        return importlib.import_module(f"numpy._core.{submodule}")
    except ImportError:
        return importlib.import_module(f"numpy.core.{submodule}")


class SafeInfoUnpickler(pickle.Unpickler):
    """An Unpickler that resolves only numpy array/scalar/dtype helpers, `_codecs.encode` and basic builtins."""

    def __init__(self, file, source: str | None = None):
        super().__init__(file)
        self.source = source

    def find_class(self, module: str, name: str):
        if (module, name) in _NUMPY_GLOBALS:
            return _NUMPY_GLOBALS[(module, name)]()
        if module == "_codecs" and name == "encode":
            import codecs

            return codecs.encode
        if module in ("builtins", "__builtin__") and name in _BUILTINS:
            return _bounded_builtin(name, self.source)
        if module == "collections" and name == "OrderedDict":
            import collections

            return collections.OrderedDict
        raise AgoInputError(self.source, f"refusing to unpickle {module}.{name} "
                                         "(only numpy arrays and plain containers are allowed in an info file)")


def _bounded_builtin(name: str, source):
    """The builtin `name`, wrapped so that a call cannot allocate more than the file itself holds:
    bytes(n) / bytearray(n) with an integer n above MAX_SIZED_ALLOC, and list/tuple/set/frozenset/dict of
    anything but an already built container (the only big iterables a pickle could pass are lazy
    ones, and `range` is not allowed at all), are refused."""
    import builtins

    fn = getattr(builtins, name)
    if name in ("bytes", "bytearray"):
        def sized(*args):
            if args and isinstance(args[0], int) and not isinstance(args[0], bool) and args[0] > MAX_SIZED_ALLOC:
                raise AgoInputError(source, f"refusing to unpickle {name}({args[0]}): a pickle may not "
                                            f"allocate more than {MAX_SIZED_ALLOC} bytes from a number")
            return fn(*args)
        return sized
    if name in ("list", "tuple", "set", "frozenset", "dict"):
        def built(*args, **kwargs):
            if args and not isinstance(args[0], (list, tuple, set, frozenset, dict, str, bytes, bytearray)):
                raise AgoInputError(source, f"refusing to unpickle {name}() of a {type(args[0]).__name__} "
                                            "(only plain containers are allowed in an info file)")
            return fn(*args, **kwargs)
        return built
    return fn


def max_info_bytes() -> int:
    import os

    env = os.environ.get("AGO_MAX_INFO_BYTES")
    return int(float(env)) if env else MAX_INFO_BYTES


def safe_load_pickle(path: str | Path):
    """Unpickle `path` with SafeInfoUnpickler; any failure is an AgoInputError naming the file.

    Refuses files over max_info_bytes() before reading them; see _bounded_builtin for the calls."""
    path = Path(path)
    if not path.is_file():
        raise AgoInputError(path, "info file not found")
    size = path.stat().st_size
    if size > max_info_bytes():
        raise AgoInputError(path, f"info file is {size / 2**30:.1f} GiB, more than ago reads "
                                  f"({max_info_bytes() / 2**30:.1f} GiB; $AGO_MAX_INFO_BYTES sets the limit)")
    data = path.read_bytes()
    try:
        return SafeInfoUnpickler(io.BytesIO(data), str(path)).load()
    except AgoInputError:
        raise
    except MemoryError:
        raise AgoInputError(path, "refusing a pickle that asks for more memory than there is") from None
    except Exception as e:  # truncated or malformed pickles raise many kinds of errors
        raise AgoInputError(path, f"not a readable pickle ({e.__class__.__name__}: {str(e)[:200]})") from None


def to_plain(obj, budget: list[int] | None = None, source=None, depth: int = 0):
    """numpy arrays/scalars inside dicts/lists -> lists/floats/ints/bools (JSON-able).

    `budget` = [values left]: a pickle can reference one list from many places (memo), which this
    copy would expand; past the budget an AgoInputError naming `source` is raised, as it is for
    containers nested deeper than MAX_INFO_DEPTH."""
    if depth > MAX_INFO_DEPTH:
        raise AgoInputError(source, f"refusing an info file nested more than {MAX_INFO_DEPTH} containers deep")
    if budget is not None:
        budget[0] -= 1
        if budget[0] < 0:
            raise AgoInputError(source, "refusing an info file whose objects expand to more values than "
                                        "the file could hold (repeated references)")
    if isinstance(obj, dict):
        return {str(k): to_plain(v, budget, source, depth + 1) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_plain(v, budget, source, depth + 1) for v in obj]
    if isinstance(obj, np.ndarray):
        if budget is not None:
            budget[0] -= int(obj.size)
            if budget[0] < 0:
                raise AgoInputError(source, "refusing an info file whose arrays hold more values than ago reads")
        if obj.ndim > MAX_INFO_DEPTH:
            raise AgoInputError(source, f"refusing an array of {obj.ndim} dimensions")
        return to_plain(obj.tolist(), budget, source, depth)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (bytes, bytearray)):
        return obj.decode("latin-1")
    return obj


def read_mmdet3d_info(pkl_path: str | Path) -> dict:
    """An info .pkl -> plain dict {"metainfo": ..., "data_list": [...]} (checked shape of the top level)."""
    budget = [200_000 + PLAIN_NODES_PER_BYTE * Path(pkl_path).stat().st_size] if Path(pkl_path).is_file() else None
    info = to_plain(safe_load_pickle(pkl_path), budget, pkl_path)
    _check_info(info, pkl_path)
    return info


def _check_info(info, source) -> None:
    if not isinstance(info, dict) or not isinstance(info.get("data_list"), list):
        raise AgoInputError(source, "not an mmdetection3d info (v1.1) file: no 'data_list' list")
    if not info["data_list"]:
        raise AgoInputError(source, "data_list is empty: the info file lists no frames")


def convert_mmdet3d_info_to_json(pkl_path: str | Path, json_out: str | Path) -> None:
    """Convert an info .pkl (read safely) into a plain JSON file with the same structure."""
    write_json(json_out, read_mmdet3d_info(pkl_path))


def load_info_json(json_path: str | Path, data_root: str | Path | None = None,
                   compensate_ego_motion: bool = True, allow_outside_root: bool = False) -> list[Frame]:
    """Frames from a JSON written by `convert_mmdet3d_info_to_json` (data_root default: the JSON's folder)."""
    json_path = Path(json_path)
    info = read_json(json_path, missing="info JSON not found")
    _check_info(info, json_path)
    return frames_from_info(info, data_root if data_root is not None else json_path.parent, json_path,
                            compensate_ego_motion=compensate_ego_motion, allow_outside_root=allow_outside_root)


def load_mmdet3d_info(pkl_path: str | Path, data_root: str | Path | None = None,
                      compensate_ego_motion: bool = True, allow_outside_root: bool = False) -> list[Frame]:
    """Frames (images, rig, keyframe LiDAR, poses) from an info .pkl (data_root default: the .pkl's folder)."""
    pkl_path = Path(pkl_path)
    info = read_mmdet3d_info(pkl_path)
    return frames_from_info(info, data_root if data_root is not None else pkl_path.parent, pkl_path,
                            compensate_ego_motion=compensate_ego_motion, allow_outside_root=allow_outside_root)


def _matrix(value, shape, source, what) -> np.ndarray:
    m = np.asarray(value, dtype=np.float64)
    if m.shape != shape or not np.all(np.isfinite(m)):
        raise AgoInputError(source, f"{what} must be a finite {shape} matrix, got shape {m.shape}")
    return m


def _rigid(value, source, what) -> np.ndarray:
    m = _matrix(value, (4, 4), source, what)
    problem = check_rigid(m)
    if problem:
        raise AgoInputError(source, f"{what} {problem}")
    return m


def _data_file(data_root: Path, folder: str, name, source, what: str, allow_outside: bool = False) -> Path:
    """mmdet3d 1.1 stores bare file names (joined with samples/<sensor>/); older infos relative paths. Either
    stays under data_root (ago_runtime.paths.inside_root), unless `allow_outside`."""
    if isinstance(name, str) and "/" not in name and "\\" not in name:
        return inside_root(data_root / "samples" / folder, name, source, what, allow_outside)
    return inside_root(data_root, name, source, what, allow_outside)


def frames_from_info(info: dict, data_root: str | Path, source: str | Path | None = None,
                     load_images: bool = True, compensate_ego_motion: bool = True,
                     allow_outside_root: bool = False) -> list[Frame]:
    """Plain info dict -> Frames. Timestamps become microseconds; cam2img keeps its top-left 3x3. Every file
    name is checked (under data_root, ago_runtime.paths) before any file is read."""
    data_root = Path(data_root)
    for n, sample in enumerate(info["data_list"]):    # names first: nothing is opened before all are checked
        try:
            _data_file(data_root, "LIDAR_TOP", sample["lidar_points"]["lidar_path"], source,
                       f"data_list[{n}].lidar_points.lidar_path", allow_outside_root)
            for cam in CAMERA_NAMES:
                _data_file(data_root, cam, sample["images"][cam]["img_path"], source,
                           f"data_list[{n}].images.{cam}.img_path", allow_outside_root)
        except (KeyError, TypeError) as e:
            raise AgoInputError(source, f"data_list[{n}] misses a field ({e})") from None
    frames = []
    for n, sample in enumerate(info["data_list"]):
        where = f"data_list[{n}]"
        try:
            images_info = sample["images"]
            lidar_info = sample["lidar_points"]
            token = str(sample.get("token", n))
            timestamp = int(round(float(sample.get("timestamp", 0.0)) * 1e6))
            ego2global = _rigid(sample["ego2global"], source, f"{where}.ego2global")
            lidar2ego = _rigid(lidar_info["lidar2ego"], source, f"{where}.lidar_points.lidar2ego")
            lidar_path = _data_file(data_root, "LIDAR_TOP", lidar_info["lidar_path"], source,
                                    f"{where}.lidar_points.lidar_path", allow_outside_root)
        except (KeyError, TypeError) as e:
            raise AgoInputError(source, f"{where} misses a field ({e})") from None
        if int(lidar_info.get("num_pts_feats", 5)) != 5:
            raise AgoInputError(source, f"{where}: ago reads 5 features per LiDAR point, "
                                        f"the info says {lidar_info.get('num_pts_feats')}")
        cameras, images, paths = [], {}, {}
        for cam in CAMERA_NAMES:
            cam_info = images_info.get(cam) if isinstance(images_info, dict) else None
            if not cam_info or "img_path" not in cam_info:
                raise AgoInputError(source, f"{where} has no {cam} image")
            k = np.asarray(cam_info.get("cam2img"), dtype=np.float64)
            if k.shape not in ((3, 3), (3, 4), (4, 4)):
                raise AgoInputError(source, f"{where}.images.{cam}.cam2img has shape {k.shape}")
            k = k[:3, :3]
            if compensate_ego_motion and cam_info.get("lidar2cam") is not None:
                lidar2cam = _rigid(cam_info["lidar2cam"], source, f"{where}.images.{cam}.lidar2cam")
                cam2ego = lidar2ego @ np.linalg.inv(lidar2cam)
            else:
                cam2ego = _rigid(cam_info.get("cam2ego"), source, f"{where}.images.{cam}.cam2ego")
            path = _data_file(data_root, cam, cam_info["img_path"], source, f"{where}.images.{cam}.img_path",
                              allow_outside_root)
            paths[cam] = str(path)
            if load_images:
                images[cam] = read_jpeg_rgb(path)
                height, width = images[cam].shape[:2]
            else:
                height, width = read_jpeg_rgb(path).shape[:2]
            cameras.append(Camera(cam, k, cam2ego, width, height))
        rig = Rig(cameras)
        rig.validate(str(source))
        sweep = LidarSweep(read_lidar_bin(lidar_path), lidar2ego, ego2global, timestamp, str(lidar_path))
        scene = str(sample.get("scene_token", ""))
        frames.append(Frame(token=token, scene=scene, timestamp=timestamp, rig=rig, ego2global=ego2global,
                            images=images, image_paths=paths, sweeps=[sweep]))
    return frames
