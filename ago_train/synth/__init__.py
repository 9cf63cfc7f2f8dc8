"""`ago synth`: a procedural synthetic driving world rendered like nuScenes.

Modules: config (SynthConfig), world (scene layout, moving agents), raycast (analytic primitives),
render (six cameras), lidar (32-beam spinning LiDAR), occupancy (Occ3D GT), generate (driver).
numpy + opencv only.
"""

from .config import SynthConfig

__all__ = ["SynthConfig"]
