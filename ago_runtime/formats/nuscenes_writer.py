"""Write a dataset in the nuScenes format (what `ago synth` produces), readable by `NuScenesDataset`
and by the official nuscenes-devkit.

Takes, per keyframe: the ego pose (ego2global, 4x4, metres), a `Rig`, six RGB uint8 images, one LiDAR
sweep ((N, 5) float32 [x, y, z, intensity, ring] in the LiDAR frame) with its lidar2ego, 3D boxes in the
global frame, optional Occ3D ground truth and optional per-pixel extras (semantics, depth).

Gives, under `root`:
- `<version>/*.json`: the thirteen nuScenes tables (attribute, calibrated_sensor, category, ego_pose,
  instance, log, map, sample, sample_annotation, sample_data, scene, sensor, visibility), linked as in
  nuScenes (prev/next chains per scene, first/last tokens, nbr_* counts, quaternions [w, x, y, z]);
  written at `close()`.
- `maps/<token>.png`: one 0.1 m/pixel mask per location (255 along the ego trajectories, a stand-in
  for nuScenes' drivable-area prior; global (0, 0) is the image's bottom-left corner as in nuScenes,
  so only positive global coordinates appear on it).
- `samples/CAM_*/<log>__<CAM>__<timestamp>.jpg` (JPEG quality 95) and
  `samples/LIDAR_TOP/<log>__LIDAR_TOP__<timestamp>.pcd.bin` (float32, N x 5), written as samples come.
- `gts/<scene name>/<sample token>/labels.npz` (Occ3D GT, `Occ3DLabels.save`).
- `synthetic/semantic/<CAM>/<jpg stem>.png` (uint8 Occ3D ids, 255 = none) and
  `synthetic/depth/<CAM>/<jpg stem>.png` (uint16 centimetres, 0 = none; depths clipped to 655.35 m).
- `splits.json`: {"train": [scene names], "val": [scene names], ...}.

Every file goes through a temporary file + rename. Tokens are md5 hex digests of names (scene name,
timestamp, channel...), so the same inputs give a byte-identical dataset. All cameras of a keyframe
share the keyframe's timestamp and ego pose (a synthetic rig is perfectly synchronised). Only
keyframes are written unless `add_sweep` adds non-key LiDAR sweeps (`ago synth --sweeps-between N`,
off by default), under `sweeps/LIDAR_TOP/`; box velocities are not stored (nuScenes has no such
field: the devkit derives them from the annotation chain).
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ago_runtime.atomic import write_bytes, write_json
from ago_runtime.geometry.camera import CAMERA_NAMES, Rig
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.nuscenes_schema import (ATTRIBUTES, CATEGORIES, CATEGORY_NAMES, LIDAR_CHANNEL, TABLE_NAMES,
                              VISIBILITY_LEVELS, check_rigid, matrix_to_record, yaw_to_quaternion)
from ago_runtime.formats.occ3d import Occ3DLabels, labels_path
from ago_runtime.formats.synthetic_maps import write_png, write_synthetic_maps

JPEG_QUALITY = 95
MAP_RESOLUTION = 0.1      # metres per map-mask pixel, as nuScenes
MAP_MAX_PIXELS = 8192     # map masks are cut at this many pixels per side
ROAD_WIDTH_M = 8.0        # width of the trajectory drawn on the map mask


@dataclass
class BoxAnnotation:
    """One 3D box of one keyframe, in the global frame (as nuScenes' sample_annotation)."""

    category: str          # nuScenes category name, e.g. "vehicle.car", "human.pedestrian.adult"
    instance: str          # stable id of the object across a scene's frames
    center: np.ndarray     # (3,) global frame, metres
    size: np.ndarray       # (3,) width, length, height (nuScenes wlh), metres
    yaw: float             # rotation about global z, radians
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))  # (2,) m/s global x, y
    num_lidar_pts: int = 0
    visibility: int = 4    # 1..4 = v0-40, v40-60, v60-80, v80-100
    attributes: tuple[str, ...] | None = None  # None: derived from the category and the speed


def _token(*parts) -> str:
    """Deterministic 32-hex-digit token from names (nuScenes tokens look the same)."""
    return hashlib.md5("/".join(str(p) for p in parts).encode("utf-8")).hexdigest()


def _safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]", "-", text)


def default_attributes(category: str, velocity: np.ndarray) -> tuple[str, ...]:
    """nuScenes gives vehicles, cycles and pedestrians exactly one attribute; pick it from the speed."""
    speed = float(np.linalg.norm(np.asarray(velocity, dtype=np.float64)[:2]))
    if category in ("vehicle.bicycle", "vehicle.motorcycle"):
        return ("cycle.with_rider",) if speed > 0.5 else ("cycle.without_rider",)
    if category.startswith("vehicle.") and category != "vehicle.ego":
        return ("vehicle.moving",) if speed > 0.5 else ("vehicle.parked",)
    if category.startswith("human.pedestrian."):
        return ("pedestrian.moving",) if speed > 0.3 else ("pedestrian.standing",)
    return ()


class NuScenesWriter:
    """Collects scenes and keyframes, writes sample files at once and the tables at `close()`."""

    def __init__(self, root: str | Path, version: str = "v1.0-trainval", camera_names=CAMERA_NAMES):
        """camera_names: the rig's camera channels (default nuScenes' six), each sample gives these cameras."""
        self.root = Path(root)
        self.camera_names = tuple(camera_names)
        self.version = version
        self._closed = False
        self._scenes: dict[str, dict] = {}          # scene token -> scene record (+ private keys)
        self._logs: dict[str, dict] = {}
        self._samples: list[dict] = []
        self._sample_data: list[dict] = []
        self._ego_poses: list[dict] = []
        self._calibrated: dict[str, dict] = {}
        self._annotations: list[dict] = []
        self._instances: dict[str, dict] = {}
        self._by_token: dict[str, dict] = {}        # sample/sample_data/annotation token -> record
        self._last_sd: dict[tuple[str, str], str] = {}      # (scene token, channel) -> sample_data token
        self._last_ann: dict[tuple[str, str], str] = {}     # (scene token, instance id) -> annotation token
        self._trajectories: dict[str, dict[str, list]] = {}  # location -> scene token -> ego xy positions
        self._sensors = {ch: {"token": _token("sensor", ch), "channel": ch, "modality": "camera"}
                         for ch in self.camera_names}
        self._sensors[LIDAR_CHANNEL] = {"token": _token("sensor", LIDAR_CHANNEL), "channel": LIDAR_CHANNEL,
                                        "modality": "lidar"}
        self._category_tokens = {name: _token("category", name) for name in CATEGORY_NAMES}
        self._attribute_tokens = {name: _token("attribute", name) for name, _ in ATTRIBUTES}

    # ------------------------------------------------------------------ scenes
    def add_scene(self, name: str, description: str = "", location: str = "synthetic") -> str:
        """Start a scene (and its log); returns the scene token."""
        self._check_open()
        token = _token("scene", name)
        if token in self._scenes:
            raise AgoInputError(self.root, f"scene {name!r} was already added")
        logfile = _safe_name(f"ago-{location}-{name}")
        log_token = _token("log", name)
        self._logs[log_token] = {"token": log_token, "logfile": logfile, "vehicle": "ago-synthetic",
                                 "date_captured": "2026-01-01", "location": location}
        self._scenes[token] = {"token": token, "log_token": log_token, "nbr_samples": 0,
                               "first_sample_token": "", "last_sample_token": "", "name": name,
                               "description": description, "_samples": [], "_logfile": logfile,
                               "_location": location}
        return token

    # ------------------------------------------------------------------ samples
    def _check_poses(self, where: str, ego2global: np.ndarray, lidar2ego: np.ndarray) -> None:
        """AgoInputError naming `where` unless both transforms are rigid (rotation + translation)."""
        for what, m in (("ego2global", ego2global), ("lidar2ego", lidar2ego)):
            problem = check_rigid(m)
            if problem:
                raise AgoInputError(self.root, f"{where}: {what} {problem}")

    def add_sample(self, scene_token: str, timestamp_us: int, ego2global: np.ndarray, rig: Rig,
                   images: dict[str, np.ndarray], lidar_points: np.ndarray, lidar2ego: np.ndarray,
                   annotations=(), gt: Occ3DLabels | None = None, extras: dict | None = None) -> str:
        """Write one keyframe's files and remember its records; returns the sample token.

        images: camera -> (H, W, 3) uint8 RGB at the rig camera's size; lidar_points: (N, 5) float32 in
        the LiDAR frame; extras: {"semantic": {cam: (H, W) uint8}, "depth": {cam: (H, W) float32 m}}.
        """
        self._check_open()
        scene = self._scenes.get(scene_token)
        if scene is None:
            raise AgoInputError(self.root, f"unknown scene token {scene_token!r} (call add_scene first)")
        timestamp_us = int(timestamp_us)
        if scene["_samples"] and timestamp_us <= self._by_token[scene["_samples"][-1]]["timestamp"]:
            raise AgoInputError(self.root, f"scene {scene['name']!r}: timestamps must increase "
                                           f"({timestamp_us} after {self._by_token[scene['_samples'][-1]]['timestamp']})")
        self._check_poses(f"scene {scene['name']!r} at {timestamp_us}", ego2global, lidar2ego)
        rig.validate(str(self.root))
        if tuple(rig.names) != self.camera_names:
            raise AgoInputError(self.root, f"the rig's cameras {rig.names} are not the writer's {list(self.camera_names)}")
        points = np.asarray(lidar_points)
        if points.ndim != 2 or points.shape[1] != 5:
            raise AgoInputError(self.root, f"lidar_points must be (N, 5), got {points.shape}")
        for cam in rig:
            img = images.get(cam.name)
            if img is None:
                raise AgoInputError(self.root, f"no image for {cam.name}")
            if img.dtype != np.uint8 or img.shape != (cam.height, cam.width, 3):
                raise AgoInputError(self.root, f"{cam.name} image must be ({cam.height}, {cam.width}, 3) uint8, "
                                               f"got {img.shape} {img.dtype}")

        sample_token = _token("sample", scene["name"], timestamp_us)
        logfile = scene["_logfile"]
        sample = {"token": sample_token, "timestamp": timestamp_us, "prev": "", "next": "",
                  "scene_token": scene_token}
        if scene["_samples"]:
            prev = self._by_token[scene["_samples"][-1]]
            prev["next"] = sample_token
            sample["prev"] = prev["token"]
        else:
            scene["first_sample_token"] = sample_token
        scene["last_sample_token"] = sample_token
        scene["nbr_samples"] += 1
        scene["_samples"].append(sample_token)
        self._samples.append(sample)
        self._by_token[sample_token] = sample
        self._trajectories.setdefault(scene["_location"], {}).setdefault(scene_token, []).append(
            np.asarray(ego2global, dtype=np.float64)[:2, 3].copy())

        extras = extras or {}
        for cam in rig:
            stem = f"{logfile}__{cam.name}__{timestamp_us}"
            filename = f"samples/{cam.name}/{stem}.jpg"
            ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(np.ascontiguousarray(images[cam.name]), cv2.COLOR_RGB2BGR),
                                   [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                raise AgoInputError(self.root / filename, "cv2 could not encode the image as JPEG")
            write_bytes(self.root / filename, jpg.tobytes())
            self._write_extras(extras, cam.name, stem, (cam.height, cam.width))
            calib = self._calibrated_sensor(scene, cam.name, cam.cam2ego,
                                            [[float(v) for v in row] for row in cam.intrinsics])
            self._add_sample_data(scene_token, cam.name, sample_token, timestamp_us, ego2global, calib,
                                  filename, "jpg", cam.width, cam.height)

        lidar_name = f"samples/{LIDAR_CHANNEL}/{logfile}__{LIDAR_CHANNEL}__{timestamp_us}.pcd.bin"
        write_bytes(self.root / lidar_name, np.ascontiguousarray(points, dtype=np.float32).tobytes())
        calib = self._calibrated_sensor(scene, LIDAR_CHANNEL, lidar2ego, [])
        self._add_sample_data(scene_token, LIDAR_CHANNEL, sample_token, timestamp_us, ego2global, calib,
                              lidar_name, "pcd", 0, 0)

        seen = set()
        for box in annotations:
            if box.instance in seen:
                raise AgoInputError(self.root, f"instance {box.instance!r} appears twice in one sample")
            seen.add(box.instance)
            self._add_annotation(scene, sample_token, box)

        if gt is not None:
            gt.save(labels_path(self.root / "gts", scene["name"], sample_token))
        return sample_token

    def add_sweep(self, scene_token: str, timestamp_us: int, ego2global: np.ndarray, lidar_points: np.ndarray,
                  lidar2ego: np.ndarray) -> str:
        """Write one NON-KEY LiDAR sweep (nuScenes' `sweeps/LIDAR_TOP/`, is_key_frame false) after the scene's
        last keyframe; returns its sample_data token. It joins the LIDAR_TOP prev/next chain, so the sweeps
        added between two keyframes are the ones the reader finds before the later keyframe
        (`NuScenesDataset.nonkey_sweeps`). Its sample_token is the keyframe before it."""
        self._check_open()
        scene = self._scenes.get(scene_token)
        if scene is None or not scene["_samples"]:
            raise AgoInputError(self.root, "a non-key sweep needs its scene and a keyframe before it (add_sample first)")
        timestamp_us = int(timestamp_us)
        last = self._by_token.get(self._last_sd.get((scene_token, LIDAR_CHANNEL), ""))
        if last is not None and timestamp_us <= int(last["timestamp"]):
            raise AgoInputError(self.root, f"scene {scene['name']!r}: sweep timestamps must increase "
                                           f"({timestamp_us} after {last['timestamp']})")
        self._check_poses(f"scene {scene['name']!r} sweep at {timestamp_us}", ego2global, lidar2ego)
        points = np.asarray(lidar_points)
        if points.ndim != 2 or points.shape[1] != 5:
            raise AgoInputError(self.root, f"lidar_points must be (N, 5), got {points.shape}")
        name = f"sweeps/{LIDAR_CHANNEL}/{scene['_logfile']}__{LIDAR_CHANNEL}__{timestamp_us}.pcd.bin"
        write_bytes(self.root / name, np.ascontiguousarray(points, dtype=np.float32).tobytes())
        calib = self._calibrated_sensor(scene, LIDAR_CHANNEL, lidar2ego, [])
        token = _token("sample_data", scene["name"], LIDAR_CHANNEL, "sweep", timestamp_us)
        self._add_sample_data(scene_token, LIDAR_CHANNEL, scene["_samples"][-1], timestamp_us, ego2global, calib,
                              name, "pcd", 0, 0, key_frame=False, token=token)
        return token

    def _write_extras(self, extras: dict, cam: str, stem: str, hw: tuple[int, int]) -> None:
        write_synthetic_maps(self.root, extras, cam, stem, hw)

    def _write_png(self, relative: str, array: np.ndarray) -> None:
        write_png(self.root / relative, array)

    def _calibrated_sensor(self, scene: dict, channel: str, sensor2ego: np.ndarray, intrinsic: list) -> str:
        record = matrix_to_record(sensor2ego)
        key = json.dumps([record, intrinsic])
        token = _token("calibrated_sensor", scene["log_token"], channel, key)
        if token not in self._calibrated:
            self._calibrated[token] = {"token": token, "sensor_token": self._sensors[channel]["token"],
                                       "translation": record["translation"], "rotation": record["rotation"],
                                       "camera_intrinsic": intrinsic}
        return token

    def _add_sample_data(self, scene_token, channel, sample_token, timestamp, ego2global, calib_token,
                         filename, fileformat, width, height, key_frame: bool = True, token: str | None = None) -> None:
        token = token or _token("sample_data", sample_token, channel)
        pose_token = _token("ego_pose", token)
        pose = matrix_to_record(ego2global)
        self._ego_poses.append({"token": pose_token, "timestamp": timestamp,
                                "rotation": pose["rotation"], "translation": pose["translation"]})
        record = {"token": token, "sample_token": sample_token, "ego_pose_token": pose_token,
                  "calibrated_sensor_token": calib_token, "timestamp": timestamp, "fileformat": fileformat,
                  "is_key_frame": bool(key_frame), "height": int(height), "width": int(width), "filename": filename,
                  "prev": "", "next": ""}
        prev_token = self._last_sd.get((scene_token, channel))
        if prev_token:
            self._by_token[prev_token]["next"] = token
            record["prev"] = prev_token
        self._last_sd[(scene_token, channel)] = token
        self._sample_data.append(record)
        self._by_token[token] = record

    def _add_annotation(self, scene: dict, sample_token: str, box: BoxAnnotation) -> None:
        if box.category not in self._category_tokens:
            raise AgoInputError(self.root, f"unknown nuScenes category {box.category!r} "
                                           f"(one of {', '.join(CATEGORY_NAMES)})")
        if str(int(box.visibility)) not in VISIBILITY_LEVELS:
            raise AgoInputError(self.root, f"visibility must be 1..4, got {box.visibility}")
        attributes = box.attributes if box.attributes is not None else default_attributes(box.category, box.velocity)
        for a in attributes:
            if a not in self._attribute_tokens:
                raise AgoInputError(self.root, f"unknown nuScenes attribute {a!r}")
        center = np.asarray(box.center, dtype=np.float64).reshape(3)
        size = np.asarray(box.size, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(center)) and np.all(np.isfinite(size)) and np.all(size > 0)
                and np.isfinite(box.yaw)):
            raise AgoInputError(self.root, f"box of instance {box.instance!r} has a non-finite or empty geometry")

        token = _token("sample_annotation", sample_token, box.instance)
        instance_token = _token("instance", scene["name"], box.instance)
        instance = self._instances.get(instance_token)
        if instance is None:
            instance = {"token": instance_token, "category_token": self._category_tokens[box.category],
                        "nbr_annotations": 0, "first_annotation_token": token, "last_annotation_token": token}
            self._instances[instance_token] = instance
        elif instance["category_token"] != self._category_tokens[box.category]:
            raise AgoInputError(self.root, f"instance {box.instance!r} changes category to {box.category!r}")
        record = {"token": token, "sample_token": sample_token, "instance_token": instance_token,
                  "visibility_token": str(int(box.visibility)),
                  "attribute_tokens": [self._attribute_tokens[a] for a in attributes],
                  "translation": [float(v) for v in center], "size": [float(v) for v in size],
                  "rotation": [float(v) for v in yaw_to_quaternion(float(box.yaw))],
                  "prev": "", "next": "", "num_lidar_pts": int(box.num_lidar_pts), "num_radar_pts": 0}
        key = (scene["token"], box.instance)
        prev_token = self._last_ann.get(key)
        if prev_token:
            self._by_token[prev_token]["next"] = token
            record["prev"] = prev_token
        self._last_ann[key] = token
        instance["nbr_annotations"] += 1
        instance["last_annotation_token"] = token
        self._annotations.append(record)
        self._by_token[token] = record

    # ------------------------------------------------------------------ close
    def close(self, splits: dict[str, list[str]] | None = None) -> None:
        """Write the map masks, the thirteen tables and splits.json (default: every scene in "train")."""
        self._check_open()
        names = [s["name"] for s in self._scenes.values()]
        for s in self._scenes.values():
            if s["nbr_samples"] == 0:
                raise AgoInputError(self.root, f"scene {s['name']!r} has no samples")
        if splits is None:
            splits = {"train": list(names), "val": []}
        for split, scene_names in splits.items():
            unknown = sorted(set(scene_names) - set(names))
            if unknown:
                raise AgoInputError(self.root, f"split {split!r} names scenes that were not written: {unknown}")

        maps = []
        for location in sorted({log["location"] for log in self._logs.values()}):
            token = _token("map", location)
            filename = f"maps/{token}.png"
            self._write_png(filename, self._map_mask(list(self._trajectories.get(location, {}).values())))
            maps.append({"token": token, "log_tokens": [t for t, log in self._logs.items()
                                                        if log["location"] == location],
                         "category": "semantic_prior", "filename": filename})

        tables = {
            "attribute": [{"token": self._attribute_tokens[n], "name": n, "description": d} for n, d in ATTRIBUTES],
            "calibrated_sensor": list(self._calibrated.values()),
            "category": [{"token": self._category_tokens[n], "name": n, "description": d, "index": i}
                         for i, (n, d) in enumerate(CATEGORIES)],
            "ego_pose": self._ego_poses,
            "instance": list(self._instances.values()),
            "log": list(self._logs.values()),
            "map": maps,
            "sample": self._samples,
            "sample_annotation": self._annotations,
            "sample_data": self._sample_data,
            "scene": [{k: v for k, v in s.items() if not k.startswith("_")} for s in self._scenes.values()],
            "sensor": list(self._sensors.values()),
            "visibility": [{"token": t, "level": lv, "description": d} for t, (lv, d) in VISIBILITY_LEVELS.items()],
        }
        assert tuple(sorted(tables)) == TABLE_NAMES
        for name in TABLE_NAMES:
            write_json(self.root / self.version / f"{name}.json", tables[name])
        write_json(self.root / "splits.json", {k: list(v) for k, v in splits.items()})
        self._closed = True

    @staticmethod
    def _map_mask(trajectories: list[list[np.ndarray]]) -> np.ndarray:
        """uint8 mask, 0.1 m/pixel, global (0, 0) at the bottom-left; 255 along each scene's ego trajectory."""
        every = np.asarray([p for t in trajectories for p in t], dtype=np.float64).reshape(-1, 2)
        margin = 50.0
        extent = np.maximum(every.max(axis=0) + margin, 1.6) if len(every) else np.array([1.6, 1.6])
        w, h = (np.clip(np.ceil(extent / MAP_RESOLUTION), 16, MAP_MAX_PIXELS)).astype(int)
        mask = np.zeros((h, w), np.uint8)
        for xy in trajectories:
            xy = np.clip(np.asarray(xy, dtype=np.float64).reshape(-1, 2), -1e5, 1e5)
            cols = xy[:, 0] / MAP_RESOLUTION
            rows = h - xy[:, 1] / MAP_RESOLUTION
            pts = np.round(np.stack([cols, rows], axis=1)).astype(np.int32).reshape(-1, 1, 2)
            thickness = int(round(ROAD_WIDTH_M / MAP_RESOLUTION))
            cv2.polylines(mask, [pts], False, 255, thickness=thickness)
            for p in pts[:, 0]:
                cv2.circle(mask, (int(p[0]), int(p[1])), thickness // 2, 255, -1)
        return mask

    def _check_open(self) -> None:
        if self._closed:
            raise AgoInputError(self.root, "this NuScenesWriter is closed")
