"""Driver: frames of a synthetic scene in memory, or a whole dataset written in the nuScenes layout.

`generate_scene(config, scene_index)` yields one dict per keyframe (nothing written):
  scene (name), scene_index, frame_index, timestamp_us (int, 2 Hz), ego2global (4,4),
  rig (Rig at the configured image size), images {cam: (H,W,3) uint8 RGB},
  lidar_points (N,5) float32 LiDAR frame [x,y,z,intensity,ring], lidar2ego (4,4),
  annotations [BoxAnnotation] (global frame), gt (Occ3DLabels on config.grid()),
  extras {"semantic": {cam: (H,W) uint8 id of gt's class table, 255 = sky}, "depth": {cam: (H,W) float32 m, 0 = none}},
  lidar_classes (N,) uint8 Occ3D class of each LiDAR return (for checks),
  sweeps [{timestamp_us, ego2global, lidar_points}]: the `config.sweeps_between` non-key LiDAR sweeps
  between the previous keyframe and this one (empty by default and for the first keyframe).
`write_dataset(config, out)` writes every scene through `ago_runtime.formats.nuscenes_writer.NuScenesWriter`
(the last `val_fraction` of the scenes form the val split) and returns a small summary dict.
The frames hold the cameras of `config.rig_name` (synth/rigs.py). With the Occ3D-Waymo layout (`config.layout_name()`,
the default of the "waymo" and "front" rigs) `gt` is `Occ3DWaymoLabels` (synth/waymo_labels.py) and `write_dataset` writes it
through `ago_runtime.formats.occ3d_waymo_writer.Occ3DWaymoWriter` (keyframe LiDAR in the ego frame, per-pixel
extras with Occ3D-Waymo ids (`waymo_labels.waymo_pixel_labels`); no boxes, no non-key sweeps).

Global frame = the world frame shifted by GLOBAL_OFFSET so that every pose is positive (nuScenes maps
put global (0, 0) at their bottom-left corner).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from ago_runtime.formats.nuscenes_writer import BoxAnnotation, NuScenesWriter
from ago_runtime.formats.occ3d_waymo_writer import Occ3DWaymoWriter
from ago_runtime.progress import track

from .config import SynthConfig
from .lidar import lidar_directions, scan_lidar
from .occupancy import occupancy_gt, occupancy_gt_waymo
from .raycast import PrimitiveSet
from .render import CameraRays, render_camera
from .waymo_labels import waymo_pixel_labels
from .world import World, build_world

GLOBAL_OFFSET = np.array([400.0, 400.0, 0.0])
TIMESTAMP_BASE_US = 1_600_000_000_000_000
ANNOTATION_RADIUS = 55.0  # objects farther than this from the ego (m, xy) are not annotated


def _to_global(world2: np.ndarray) -> np.ndarray:
    m = world2.copy()
    m[:3, 3] += GLOBAL_OFFSET
    return m


def _visible_subset(prims: PrimitiveSet, ego_xy: np.ndarray, radius: float):
    lo, hi = prims.aabb()
    gap = np.maximum(np.maximum(lo[:, :2] - ego_xy, ego_xy - hi[:, :2]), 0)
    keep = np.hypot(gap[:, 0], gap[:, 1]) < radius
    return prims.subset(keep), (lo[keep], hi[keep])


def _visibility_level(visible: float, total: float) -> int:
    if total <= 0:
        return 1
    f = visible / total
    return 1 if f < 0.4 else 2 if f < 0.6 else 3 if f < 0.8 else 4


def generate_scene(config: SynthConfig, scene_index: int, world: World | None = None) -> Iterator[dict]:
    world = world if world is not None else build_world(config, scene_index)
    rig = config.rig()
    rays = {cam.name: CameraRays(cam) for cam in rig}
    grid = config.grid()
    lidar_dirs = lidar_directions(config)
    lidar2ego = config.lidar2ego()
    name = config.scene_name(scene_index)
    scene_rng = np.random.default_rng([config.seed, scene_index, 3])
    exposure = {cam.name: scene_rng.uniform(0.92, 1.08) for cam in rig}
    n_obj = len(world.obj_category)
    waymo = config.layout_name() != "nuscenes"
    for f in range(config.frames_per_scene):
        time_s = f * config.keyframe_interval_s
        rng = np.random.default_rng([config.seed, scene_index, f, 11])
        ego2world = world.ego_pose(time_s)
        prims, aabb = _visible_subset(world.primitives_at(time_s), ego2world[:2, 3], config.render_distance)
        images, semantic, depth = {}, {}, {}
        vis_px = np.zeros(n_obj + 1)
        any_px = np.zeros(n_obj + 1)
        for cam in rig:
            rgb, sem, dep, ids, any_hits = render_camera(world, prims, aabb, cam, rays[cam.name], ego2world, rng,
                                                         config.image_noise_std, exposure[cam.name])
            if waymo:   # per-pixel ids in the ground truth's table (Occ3D-Waymo), refined by material as its voxels
                sem = waymo_pixel_labels(sem, ids, prims.material)
            images[cam.name], semantic[cam.name], depth[cam.name] = rgb, sem, dep
            hit_ids = ids[ids >= 0]
            # object index -1 (scenery) goes to the last, unused slot
            vis_px += np.bincount(prims.obj[hit_ids] % (n_obj + 1), minlength=n_obj + 1)
            any_px += np.bincount(prims.obj % (n_obj + 1), weights=any_hits, minlength=n_obj + 1)
        scan = scan_lidar(world, prims, aabb, config, ego2world, rng, lidar_dirs)
        sweeps = []   # non-key LiDAR sweeps between the previous keyframe and this one, oldest first
        if f > 0 and config.sweeps_between > 0:
            dt = config.keyframe_interval_s / (config.sweeps_between + 1)
            for k in range(1, config.sweeps_between + 1):
                t_k = (f - 1) * config.keyframe_interval_s + k * dt
                pose_k = world.ego_pose(t_k)
                prims_k, aabb_k = _visible_subset(world.primitives_at(t_k), pose_k[:2, 3], config.render_distance)
                rng_k = np.random.default_rng([config.seed, scene_index, f, 13, k])
                sweeps.append({"timestamp_us": TIMESTAMP_BASE_US + scene_index * 3_600_000_000 + int(round(t_k * 1e6)),
                               "ego2global": _to_global(pose_k),
                               "lidar_points": scan_lidar(world, prims_k, aabb_k, config, pose_k, rng_k,
                                                          lidar_dirs).points})
        gt_of = occupancy_gt_waymo if waymo else occupancy_gt
        gt = gt_of(world, prims, ego2world, grid, rig, depth, scan.origin_world, scan.points_world,
                   config.gt_samples_per_axis)
        # annotations
        centres = world.object_centres(time_s)
        near = np.hypot(*(centres[:, :2] - ego2world[:2, 3]).T) < ANNOTATION_RADIUS
        pts_per_obj = np.bincount(scan.obj[scan.obj >= 0], minlength=n_obj)
        boxes = []
        for o in np.nonzero(near)[0]:
            if pts_per_obj[o] == 0 and vis_px[o] == 0:
                continue
            boxes.append(BoxAnnotation(
                category=world.obj_category[o], instance=f"{name}-obj{o:05d}", center=centres[o] + GLOBAL_OFFSET,
                size=world.obj_size[o].copy(), yaw=float(world.obj_yaw[o]), velocity=world.obj_vel[o].copy(),
                num_lidar_pts=int(pts_per_obj[o]), visibility=_visibility_level(vis_px[o], any_px[o])))
        yield {
            "scene": name, "scene_index": scene_index, "frame_index": f,
            "timestamp_us": TIMESTAMP_BASE_US + scene_index * 3_600_000_000 + int(round(time_s * 1e6)),
            "ego2global": _to_global(ego2world), "rig": rig, "images": images,
            "lidar_points": scan.points, "lidar2ego": lidar2ego, "annotations": boxes, "gt": gt,
            # sky has no depth: 0 in the extras, as the dataset format says (the renderer uses a far value)
            "extras": {"semantic": semantic,
                       "depth": {c: np.where(semantic[c] == 255, 0.0, d).astype(np.float32) for c, d in depth.items()}},
            "lidar_classes": scan.classes,
            "sweeps": sweeps,
        }


def _scene_frames(args: tuple[SynthConfig, int]) -> list[dict]:
    """All keyframes of one scene (a worker process's job for `write_dataset(..., jobs > 1)`)."""
    config, scene_index = args
    return list(generate_scene(config, scene_index))


def _scenes(config: SynthConfig, jobs: int):
    """(scene index, its frames) for every scene, rendered here or in `jobs` worker processes."""
    if jobs <= 1 or config.num_scenes <= 1:
        for s in range(config.num_scenes):
            yield s, generate_scene(config, s)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=min(jobs, config.num_scenes), mp_context=mp.get_context("spawn")) as ex:
        yield from enumerate(ex.map(_scene_frames, [(config, s) for s in range(config.num_scenes)]))


def write_waymo_layout(config: SynthConfig, out: str | Path, progress: bool = True, jobs: int = 1) -> dict:
    """Write `config.num_scenes` scenes under `out` in the Occ3D-Waymo layout; returns a summary.

    Train scenes are `training/000, 001, ...`, val scenes `validation/000, ...` (numbered per split, as
    Occ3D-Waymo); splits.json lists the folder names as `training/000`."""
    out = Path(out)
    rig = config.rig()
    writer = Occ3DWaymoWriter(out, [c.name for c in rig])
    val = set(config.val_scene_indices())
    splits = {"train": [], "val": []}
    number = {"training": 0, "validation": 0}
    samples = points = 0

    def frames():
        for s, scene in _scenes(config, jobs):
            split = "validation" if s in val else "training"
            index = number[split]
            number[split] += 1
            splits["val" if split == "validation" else "train"].append(f"{split}/{index:03d}")
            for frame in scene:
                yield split, index, frame

    total = config.num_scenes * config.frames_per_scene
    it = track(frames(), "synth", total=total) if progress else frames()
    for split, index, fr in it:
        writer.add_frame(split, index, fr["frame_index"], fr["ego2global"], fr["rig"], fr["images"], fr["gt"],
                         timestamp_us=fr["timestamp_us"], lidar_points=fr["lidar_points"], lidar2ego=fr["lidar2ego"],
                         extras=fr["extras"])
        samples += 1
        points += len(fr["lidar_points"])
    writer.close(splits)
    return {"out": str(out), "scenes": config.num_scenes, "splits": splits, "samples": samples,
            "annotations": 0, "lidar_points": points}


def write_dataset(config: SynthConfig, out: str | Path, progress: bool = True, jobs: int = 1) -> dict:
    """Write `config.num_scenes` scenes under `out` in the nuScenes layout; returns a summary.

    `jobs` > 1 renders whole scenes in that many worker processes (each scene depends only on
    (seed, scene index), so the dataset is byte-for-byte the same); the writer stays in this process.
    `config.layout_name()` "occ3d-waymo": the Occ3D-Waymo layout instead (`write_waymo_layout`)."""
    if config.layout_name() == "occ3d-waymo":
        return write_waymo_layout(config, out, progress=progress, jobs=jobs)
    out = Path(out)
    writer = NuScenesWriter(out, version=config.version, camera_names=config.rig().names)
    val = set(config.val_scene_indices())
    splits = {"train": [], "val": []}
    counts = {"samples": 0, "annotations": 0, "lidar_points": 0}

    def frames():
        for s, scene in _scenes(config, jobs):
            name = config.scene_name(s)
            token = writer.add_scene(name, description=f"ago synth seed {config.seed} scene {s}")
            splits["val" if s in val else "train"].append(name)
            for frame in scene:
                frame["scene_token"] = token
                yield frame

    total = config.num_scenes * config.frames_per_scene
    it = track(frames(), "synth", total=total) if progress else frames()
    for fr in it:
        for sw in fr["sweeps"]:   # non-key sweeps recorded before this keyframe (config.sweeps_between)
            writer.add_sweep(fr["scene_token"], sw["timestamp_us"], sw["ego2global"], sw["lidar_points"],
                             fr["lidar2ego"])
        writer.add_sample(fr["scene_token"], fr["timestamp_us"], fr["ego2global"], fr["rig"], fr["images"],
                          fr["lidar_points"], fr["lidar2ego"], annotations=fr["annotations"], gt=fr["gt"],
                          extras=fr["extras"])
        counts["samples"] += 1
        counts["annotations"] += len(fr["annotations"])
        counts["lidar_points"] += len(fr["lidar_points"])
    writer.close(splits=splits)
    return {"out": str(out), "scenes": config.num_scenes, "splits": splits, **counts}
