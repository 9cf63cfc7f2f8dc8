"""`Frame`: one keyframe as every part of ago sees it, whether read from real nuScenes or `ago synth`.

Conventions:
- images: dict camera name -> (H, W, 3) uint8 **RGB** array;
- LiDAR points: (N, 5) float32 [x, y, z, intensity, ring] in the LiDAR frame, as nuScenes' .pcd.bin;
- poses: 4x4 float64 matrices, names say the frames (lidar2ego, ego2global);
- the keyframe's ego frame is the frame of the Occ3D grid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ago_runtime.geometry.camera import Rig
from ago_runtime.formats.occ3d import Occ3DLabels


@dataclass
class LidarSweep:
    points: np.ndarray          # (N, 5) float32, LiDAR frame
    lidar2ego: np.ndarray       # (4, 4)
    ego2global: np.ndarray      # (4, 4) ego pose at this sweep's timestamp
    timestamp: int = 0          # microseconds
    path: str | None = None     # file it came from, for error messages

    def points_in(self, target_ego2global: np.ndarray) -> np.ndarray:
        """(N, 3) float64 points in the ego frame whose pose is `target_ego2global` (e.g. a keyframe's)."""
        m = np.linalg.inv(target_ego2global) @ self.ego2global @ self.lidar2ego
        p = self.points[:, :3].astype(np.float64)
        return p @ m[:3, :3].T + m[:3, 3]

    def points_ego(self) -> np.ndarray:
        """(N, 3) points in this sweep's own ego frame."""
        return self.points_in(self.ego2global)


@dataclass
class Frame:
    token: str                         # nuScenes sample token
    scene: str                         # scene name, e.g. "scene-0061"
    timestamp: int                     # microseconds
    rig: Rig                           # calibration at the images' native size
    ego2global: np.ndarray             # (4, 4) ego pose of the keyframe (its LiDAR timestamp)
    images: dict[str, np.ndarray] = field(default_factory=dict)   # camera -> (H, W, 3) uint8 RGB
    image_paths: dict[str, str] = field(default_factory=dict)     # camera -> file it came from
    sweeps: list[LidarSweep] = field(default_factory=list)        # sweeps[0] is the keyframe's own
    gt: Occ3DLabels | None = None
    extras: dict = field(default_factory=dict)  # e.g. synthetic per-pixel semantics/depth maps

    @property
    def lidar(self) -> LidarSweep:
        return self.sweeps[0]

    def image_path(self, camera: str) -> Path:
        return Path(self.image_paths[camera])
