"""`SynthConfig`: every parameter of the synthetic world, its sensors and its output.

Build the nouns from it: `config.grid()` (Occ3D grid in the ego frame), `config.rig()` (the cameras of
`config.rig_name` at the configured image size: six nuScenes-like ones by default, see synth/rigs.py),
`config.lidar2ego()`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ago_runtime.geometry.camera import Rig
from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.grid import Grid

from .rigs import LAYOUT_OF_RIG, LAYOUTS, RIGS, make_rig


@dataclass
class SynthConfig:
    # dataset
    seed: int = 0
    num_scenes: int = 10
    frames_per_scene: int = 40          # keyframes per scene (nuScenes: ~40 = 20 s at 2 Hz)
    keyframe_interval_s: float = 0.5    # 2 Hz keyframes
    val_fraction: float = 0.2           # the last ceil(20%) of the scenes go to the val split
    scene_prefix: str = "synth"
    version: str = "v1.0-trainval"
    # cameras
    rig_name: str = "nuscenes"          # "nuscenes", "waymo" or "front" (synth/rigs.py)
    layout: str = ""                    # "nuscenes" or "occ3d-waymo"; "" = the rig's own (LAYOUT_OF_RIG)
    image_width: int = 800
    image_height: int = 450
    image_noise_std: float = 3.0        # per-pixel Gaussian noise (8-bit levels)
    render_distance: float = 130.0      # objects farther than this (AABB distance, m) are not drawn
    # occupancy grid (ego frame, Occ3D range)
    grid_shape: tuple[int, int, int] = (200, 200, 16)
    gt_samples_per_axis: int = 2        # sub-voxel samples per axis for the any-occupied rule
    # LiDAR (HDL-32E like, nuScenes LIDAR_TOP mounting)
    lidar_beams: int = 32
    lidar_azimuth_steps: int = 1084
    lidar_elevation_min_deg: float = -30.67
    lidar_elevation_max_deg: float = 10.67
    lidar_max_range: float = 80.0
    lidar_range_noise: float = 0.02     # metres, Gaussian
    lidar_position: tuple[float, float, float] = (0.943, 0.0, 1.84)
    sweeps_between: int = 0             # non-key LiDAR sweeps written between two keyframes (0 = keyframes
                                        # only, the default; nuScenes: ~9, LiDAR 20 Hz vs keyframes 2 Hz)
    # world
    world_size: float = 440.0           # side of the square city (m) around the start of the ego route (grown for long routes)
    block_min: float = 40.0             # spacing of parallel roads (m)
    block_max: float = 75.0
    ego_speed_min: float = 3.0          # m/s
    ego_speed_max: float = 8.0
    moving_vehicles_per_100m_lane: float = 2.0
    pedestrians_per_100m_sidewalk: float = 3.0
    parked_fill: float = 0.7           # fraction of parking-strip length filled with parked vehicles

    def __post_init__(self):
        self.grid_shape = tuple(int(v) for v in self.grid_shape)
        self.lidar_position = tuple(float(v) for v in self.lidar_position)
        problems = []
        if self.num_scenes < 1:
            problems.append("num_scenes must be >= 1")
        if self.frames_per_scene < 1:
            problems.append("frames_per_scene must be >= 1")
        if self.image_width < 16 or self.image_height < 16:
            problems.append("image size must be at least 16x16")
        if len(self.grid_shape) != 3 or min(self.grid_shape) < 1:
            problems.append(f"grid shape must be three positive ints, got {self.grid_shape}")
        if not 0.0 <= self.val_fraction < 1.0:
            problems.append("val_fraction must be in [0, 1)")
        if self.gt_samples_per_axis < 1:
            problems.append("gt_samples_per_axis must be >= 1")
        if self.sweeps_between < 0:
            problems.append("sweeps_between must be >= 0")
        if self.lidar_beams < 1 or self.lidar_azimuth_steps < 8:
            problems.append("the LiDAR needs >= 1 beam and >= 8 azimuth steps")
        if self.rig_name not in RIGS:
            problems.append(f"rig must be one of {', '.join(RIGS)}, got {self.rig_name!r}")
        elif self.layout not in ("",) + LAYOUTS:
            problems.append(f"layout must be one of {', '.join(LAYOUTS)}, got {self.layout!r}")
        elif self.layout_name() == "occ3d-waymo" and self.num_scenes > 1000:
            problems.append("the Occ3D-Waymo layout numbers scenes with three digits: at most 1000 scenes")
        if problems:
            raise AgoInputError("SynthConfig", "; ".join(problems))

    def grid(self) -> Grid:
        """The Occ3D range [-40,-40,-1, 40,40,5.4] m cut into `grid_shape` voxels (default 0.4 m)."""
        return Grid.with_shape(self.grid_shape)

    def rig(self) -> Rig:
        """The cameras of `rig_name`, in file order (synth/rigs.py)."""
        return make_rig(self.rig_name, self.image_width, self.image_height)

    def layout_name(self) -> str:
        """The dataset layout written: `layout`, or the rig's own (nuscenes -> nuScenes, waymo/front -> Occ3D-Waymo)."""
        return self.layout or LAYOUT_OF_RIG[self.rig_name]

    def lidar2ego(self) -> np.ndarray:
        """(4, 4): nuScenes' LIDAR_TOP mounting; LiDAR x = ego right (-y), LiDAR y = ego forward."""
        m = np.eye(4)
        m[:3, :3] = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # Rz(-90 deg)
        m[:3, 3] = self.lidar_position
        return m

    def lidar_elevations(self) -> np.ndarray:
        """(beams,) beam elevations in radians, lowest first (ring 0 = lowest beam)."""
        return np.deg2rad(np.linspace(self.lidar_elevation_min_deg, self.lidar_elevation_max_deg, self.lidar_beams))

    def scene_name(self, scene_index: int) -> str:
        return f"{self.scene_prefix}-{self.seed:04d}-{scene_index:04d}"

    def val_scene_indices(self) -> list[int]:
        n_val = int(np.ceil(self.val_fraction * self.num_scenes)) if self.num_scenes > 1 else 0
        n_val = min(n_val, self.num_scenes - 1)
        return list(range(self.num_scenes - n_val, self.num_scenes))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["grid_shape"] = list(self.grid_shape)
        d["lidar_position"] = list(self.lidar_position)
        return d


def parse_size(text: str, n: int, what: str) -> tuple[int, ...]:
    """'800x450' -> (800, 450); raises AgoInputError naming `what` on bad text."""
    parts = str(text).lower().replace("*", "x").split("x")
    try:
        values = tuple(int(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != n or min(values) <= 0:
        raise AgoInputError(what, f"expected {n} positive integers like {'x'.join(['8'] * n)}, got {text!r}")
    return values
