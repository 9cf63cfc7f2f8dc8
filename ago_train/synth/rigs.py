"""The camera rigs `ago synth --rig` renders, and the Occ3D-Waymo labels of the synthetic world.

- `nuscenes` (default): six nuScenes-like cameras of one size (`Rig.nuscenes_like`), nuScenes layout;
- `waymo`: Waymo's five cameras, FRONT, FRONT_LEFT, FRONT_RIGHT, SIDE_LEFT, SIDE_RIGHT (yaw 0, +45,
  -45, +90, -90 deg), each with a 50.4 deg horizontal field of view; the front three at the given
  image size, the side two as wide but SIDE_HEIGHT_RATIO (886/1280, Waymo's side/front image
  heights) as tall with the same focal length, so a shorter vertical field of view. The mounting
  positions and the field of view are our choices (no source we read states them);
- `front`: FRONT alone.
`waymo` and `front` write the Occ3D-Waymo layout with labels in `OCC3D_WAYMO` by default (docs/dataset_format.md;
the labels: synth/waymo_labels.py); `--layout nuscenes` writes any rig in the nuScenes layout instead
(its cameras as the sensor channels, Occ3D-nuScenes labels), the layout a custom rig is usually converted to.
"""

from __future__ import annotations

import numpy as np

from ago_runtime.geometry.camera import Rig, level_camera

RIGS = ("nuscenes", "waymo", "front")
LAYOUTS = ("nuscenes", "occ3d-waymo")
LAYOUT_OF_RIG = {"nuscenes": "nuscenes", "waymo": "occ3d-waymo", "front": "occ3d-waymo"}
WAYMO_CAMERAS = ("FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT")
SIDE_HEIGHT_RATIO = 886 / 1280
WAYMO_HFOV_DEG = 50.4
DEFAULT_IMAGE_SIZE = {"nuscenes": (800, 450), "waymo": (960, 640), "front": (960, 640)}
_WAYMO_MOUNT = {  # name: (x, y, z, yaw_deg) in the ego frame (ours)
    "FRONT": (1.60, 0.00, 2.10, 0.0),
    "FRONT_LEFT": (1.50, 0.10, 2.10, 45.0),
    "FRONT_RIGHT": (1.50, -0.10, 2.10, -45.0),
    "SIDE_LEFT": (1.20, 0.15, 2.10, 90.0),
    "SIDE_RIGHT": (1.20, -0.15, 2.10, -90.0),
}


def make_rig(name: str, width: int, height: int) -> Rig:
    """The rig `name`: six nuScenes cameras, Waymo's five (file order) or Waymo's front camera alone."""
    if name == "nuscenes":
        return Rig.nuscenes_like(width, height)
    names = WAYMO_CAMERAS if name == "waymo" else WAYMO_CAMERAS[:1]
    side_h = max(1, int(round(height * SIDE_HEIGHT_RATIO)))
    cams = []
    for cam in names:
        x, y, z, yaw = _WAYMO_MOUNT[cam]
        h = side_h if cam.startswith("SIDE") else height
        cams.append(level_camera(cam, x, y, z, np.deg2rad(yaw), np.deg2rad(WAYMO_HFOV_DEG), width, h))
    return Rig(cams)
