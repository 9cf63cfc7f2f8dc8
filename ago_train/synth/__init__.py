"""`ago synth`: a procedural synthetic driving world rendered like nuScenes.

Modules: config (SynthConfig); the city, by what it builds: builder (surface codes, materials, the
Builder), roads (road network, markings, ego route), blocks, buildings, vegetation, furniture (street
lights, signs, traffic lights), agents (vehicles, pedestrians, small objects), assembled by world
(World, build_world); raycast (analytic primitives), render (the rig's cameras), lidar (32-beam spinning
LiDAR), occupancy (Occ3D GT), generate (driver), cli (`ago synth`).
numpy + opencv only.
"""

from .config import SynthConfig

__all__ = ["SynthConfig"]
