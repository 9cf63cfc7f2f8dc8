"""How far apart the two camera-pose conventions put the real keyframe's LiDAR points in the images.

Reads ../shared/data/nuscenes-sample/mmdet3d_info.pkl twice (compensate_ego_motion True / False; see
docs/dataset_format.md), projects the keyframe LiDAR into each camera both ways, and prints per camera
the time between the camera and the LiDAR, how far the camera moved, and the pixel distance between
the two projections of the same points (median, 95th percentile, max). Writes the table to
benchmarks/results/ego_motion_compensation.md.

    python -m benchmarks.ego_motion_compensation
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from ago_runtime.formats.mmdet3d_info import load_mmdet3d_info, read_mmdet3d_info  # noqa: E402
from ago_runtime.atomic import write_text  # noqa: E402


def main() -> None:
    pkl = REPO.parent / "shared" / "data" / "nuscenes-sample" / "mmdet3d_info.pkl"
    if not pkl.is_file():
        sys.exit(f"{pkl} not found (the real keyframe lives in ../shared)")
    (frame,) = load_mmdet3d_info(pkl)
    (raw,) = load_mmdet3d_info(pkl, compensate_ego_motion=False)
    info = read_mmdet3d_info(pkl)["data_list"][0]
    points = frame.lidar.points_ego()
    lines = ["| camera | dt camera-LiDAR (ms) | camera moved (m) | points | median px | p95 px | max px |",
             "|---|---|---|---|---|---|---|"]
    for cam, raw_cam in zip(frame.rig, raw.rig):
        dt = (frame.timestamp / 1e6 - info["images"][cam.name]["timestamp"]) * 1e3
        moved = np.linalg.norm(cam.cam2ego[:3, 3] - raw_cam.cam2ego[:3, 3])
        uv, _, ok = cam.project(points)
        uv_raw, _, ok_raw = raw_cam.project(points)
        both = ok & ok_raw
        px = np.linalg.norm(uv[both] - uv_raw[both], axis=1)
        lines.append(f"| {cam.name} | {dt:.1f} | {moved:.3f} | {both.sum()} | {np.median(px):.1f} | "
                     f"{np.percentile(px, 95):.1f} | {px.max():.1f} |")
    table = "\n".join(lines)
    print(table)
    write_text(REPO / "benchmarks" / "results" / "ego_motion_compensation.md",
               "# Camera ego-motion compensation on the real nuScenes keyframe (scene-0061)\n\n"
               "Command: `python -m benchmarks.ego_motion_compensation` (1600x900 images; pixel distance between\n"
               "projections with `compensate_ego_motion=True` and `False`, points inside both).\n\n" + table + "\n")


if __name__ == "__main__":
    main()
