"""The procedural city of one scene, assembled: roads, blocks, scenery, movable objects and the ego route.

`build_world(config, scene_index) -> World` is deterministic in (config.seed, scene_index).
World frame = nuScenes global frame: x east, y north, z up, metres; the ground is the plane z = 0
(road level), city blocks are 0.15 m raised slabs (curbs) whose top class comes from a 2-D
surface raster (sidewalk, grass, soil, water, plaza, parking ...).

Layout: a Manhattan grid of roads (1 or 2 lanes per direction, optional parking strips, a raised
traffic island or a tram rail strip on the centre line, lane markings, zebra crossings), blocks of
type urban (buildings, walls, courtyards), park (lawn, trees, bushes, a pond, paths), parking lot
(parked cars, trucks, trailers) or construction site (excavators, barriers, cones, debris); street
furniture along every sidewalk (street lights, trees, signs, traffic lights, bins, bicycles);
parked vehicles in the parking strips; vehicles driving along lanes and pedestrians walking on
sidewalks and zebra crossings (constant velocity); a row of "points of interest" next to the ego
road (bus stop, road works, a row of barriers closing the road edge, truck + trailer, motorcycles,
bicycles, bins ...) so that every class appears near the ego in every scene. The ego drives the
inner lane of the road y = 0 in +x at a constant speed and may turn at one intersection.

What builds what: builder.py (surface codes, materials, the Builder), roads.py (road network,
markings, ego route), blocks.py (city blocks), buildings.py, vegetation.py, furniture.py (street
lights, signs, traffic lights), agents.py (vehicles, pedestrians, small objects and where they go).
This module holds `World` (the built scene: primitives, objects, rasters, route, sky) and
`build_world`, which calls them in a fixed order (the random draws, and so the city, depend on it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .agents import add_crossing_pedestrians, add_points_of_interest, add_traffic
from .blocks import add_blocks
from .builder import RASTER_RES, S_GRASS, Builder
from .config import SynthConfig
from .raycast import PrimitiveSet
from .roads import ego_route, paint_roads, road_network


@dataclass
class World:
    config: SynthConfig
    scene_index: int
    static: PrimitiveSet                 # world frame, obj = -1
    parts: PrimitiveSet                  # object-local frame, obj = object index
    obj_pos0: np.ndarray                 # (M, 2) centre at t = 0
    obj_vel: np.ndarray                  # (M, 2) m/s
    obj_yaw: np.ndarray                  # (M,)
    obj_size: np.ndarray                 # (M, 3) w, l, h
    obj_category: list                   # nuScenes category names
    surface: np.ndarray                  # (H, W) uint8 surface codes, row = y, col = x
    marking: np.ndarray                  # (H, W) uint8 0 none, 1 white, 2 yellow
    raster_origin: tuple                 # world (x, y) of the raster's cell (0, 0) corner
    route: np.ndarray                    # (K, 2) ego rear-axle path, 0.1 m steps
    route_s: np.ndarray                  # (K,) arclength
    ego_speed: float
    ego_s0: float
    sun: np.ndarray                      # (3,) unit vector towards the sun
    sky_top: np.ndarray                  # (3,) RGB 0..1
    sky_horizon: np.ndarray
    roads: list = field(default_factory=list)

    # ---- ego ---------------------------------------------------------------------------------
    def ego_pose(self, time_s: float) -> np.ndarray:
        """(4, 4) ego2global at `time_s` (ego = rear axle on the ground, x forward)."""
        s = self.ego_s0 + self.ego_speed * time_s
        x = np.interp(s, self.route_s, self.route[:, 0])
        y = np.interp(s, self.route_s, self.route[:, 1])
        xa = np.interp(s + 1.0, self.route_s, self.route[:, 0]) - np.interp(s - 1.0, self.route_s, self.route[:, 0])
        ya = np.interp(s + 1.0, self.route_s, self.route[:, 1]) - np.interp(s - 1.0, self.route_s, self.route[:, 1])
        yaw = np.arctan2(ya, xa)
        m = np.eye(4)
        m[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        m[:2, 3] = (x, y)
        return m

    # ---- objects -------------------------------------------------------------------------------
    def object_centres(self, time_s: float) -> np.ndarray:
        """(M, 3) object box centres (world) at `time_s`."""
        xy = self.obj_pos0 + self.obj_vel * time_s
        return np.concatenate([xy, self.obj_size[:, 2:3] / 2], axis=1)

    def primitives_at(self, time_s: float) -> PrimitiveSet:
        """All primitives in the world frame at `time_s`: static scenery, then object parts."""
        p = self.parts
        centres = self.object_centres(time_s)[p.obj]
        yaw = self.obj_yaw[p.obj]
        c, s = np.cos(yaw), np.sin(yaw)
        world_c = np.stack([centres[:, 0] + c * p.center[:, 0] - s * p.center[:, 1],
                            centres[:, 1] + s * p.center[:, 0] + c * p.center[:, 1],
                            centres[:, 2] + p.center[:, 2]], axis=1)
        dyn = PrimitiveSet(p.kind, world_c, p.half, p.yaw + yaw, p.cls, p.material, p.color, p.param, p.obj)
        return PrimitiveSet.concat([self.static, dyn])

    # ---- ground raster --------------------------------------------------------------------------
    def surface_at(self, xy: np.ndarray) -> np.ndarray:
        """Surface codes at world points (..., 2); outside the raster: grass."""
        col = np.floor((xy[..., 0] - self.raster_origin[0]) / RASTER_RES).astype(np.int64)
        row = np.floor((xy[..., 1] - self.raster_origin[1]) / RASTER_RES).astype(np.int64)
        H, W = self.surface.shape
        ok = (col >= 0) & (col < W) & (row >= 0) & (row < H)
        out = np.full(col.shape, S_GRASS, np.uint8)
        out[ok] = self.surface[row[ok], col[ok]]
        return out

    def raster_at(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Surface codes and marking codes at world points (x, y) (1-D arrays); outside: grass, none."""
        H, W = self.surface.shape
        col = ((x - self.raster_origin[0]) * (1.0 / RASTER_RES)).astype(np.int64)
        row = ((y - self.raster_origin[1]) * (1.0 / RASTER_RES)).astype(np.int64)
        ok = (col >= 0) & (col < W) & (row >= 0) & (row < H)
        flat = np.where(ok, row * W + np.where(ok, col, 0), 0)
        surface = np.where(ok, self.surface.ravel()[flat], S_GRASS).astype(np.uint8)
        marking = np.where(ok, self.marking.ravel()[flat], 0).astype(np.uint8)
        return surface, marking

    def marking_at(self, xy: np.ndarray) -> np.ndarray:
        col = np.floor((xy[..., 0] - self.raster_origin[0]) / RASTER_RES).astype(np.int64)
        row = np.floor((xy[..., 1] - self.raster_origin[1]) / RASTER_RES).astype(np.int64)
        H, W = self.marking.shape
        ok = (col >= 0) & (col < W) & (row >= 0) & (row < H)
        out = np.zeros(col.shape, np.uint8)
        out[ok] = self.marking[row[ok], col[ok]]
        return out


def build_world(config: SynthConfig, scene_index: int) -> World:
    rng = np.random.default_rng([config.seed, scene_index, 7])
    duration = (config.frames_per_scene - 1) * config.keyframe_interval_s
    speed = rng.uniform(config.ego_speed_min, config.ego_speed_max)
    travel = speed * duration
    half = max(config.world_size / 2, travel + 80.0)  # long scenes get a bigger city
    b = Builder(config, rng, half)
    x_start = -min(travel / 2, 60.0)

    xroads, yroads, ego_road = road_network(rng, config, half, x_start)
    roads = xroads + yroads
    route_xy, route_s = ego_route(rng, ego_road, yroads, x_start, travel)
    ego_s0 = 40.0
    paint_roads(b, roads, xroads, yroads, half)
    add_blocks(b, xroads, yroads, half, x_start)
    add_traffic(b, roads, xroads, yroads, ego_road, half, x_start)
    add_points_of_interest(b, ego_road, yroads, x_start, travel)   # every class near the ego
    add_crossing_pedestrians(b, yroads, ego_road, x_start, travel)
    world = _finish(b, config, scene_index, route_xy, route_s, speed, ego_s0, roads)
    return world


def _finish(b: Builder, config, scene_index, route_xy, route_s, speed, ego_s0, roads) -> World:
    rng = b.rng
    static = PrimitiveSet.from_rows(b.static_rows)
    parts = PrimitiveSet.from_rows(b.part_rows)
    pos0 = np.array(b.obj_pos0, float).reshape(-1, 2)
    vel = np.array(b.obj_vel, float).reshape(-1, 2)
    yaw = np.array(b.obj_yaw, float)
    size = np.array(b.obj_size, float).reshape(-1, 3)
    sun_el, sun_az = rng.uniform(np.deg2rad(25), np.deg2rad(65)), rng.uniform(-np.pi, np.pi)
    sun = np.array([np.cos(sun_el) * np.cos(sun_az), np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el)])
    overcast = rng.random() < 0.3
    sky_top = np.array([0.62, 0.64, 0.68]) if overcast else np.array([0.3, 0.5, 0.85]) * rng.uniform(0.9, 1.1)
    sky_hor = np.array([0.82, 0.83, 0.85]) if overcast else np.array([0.75, 0.83, 0.92])
    world = World(config, scene_index, static, parts, pos0, vel, yaw, size, list(b.obj_cat), b.surface, b.marking,
                  b.origin, route_xy, route_s, float(speed), ego_s0, sun, np.clip(sky_top, 0, 1), sky_hor, roads)
    # drop objects that would overlap the ego vehicle's footprint (cameras inside an object) at any time:
    # test the object's centre in the ego frame against the ego box (x in [-1, 3.8], |y| < 1) grown by the
    # object's half extents along the ego axes and a 0.4 m margin, every 0.1 s.
    duration = (config.frames_per_scene - 1) * config.keyframe_interval_s
    times = np.arange(0.0, duration + 0.11, 0.1)
    poses = np.array([world.ego_pose(t) for t in times])                  # (T, 4, 4)
    ego_xy, ego_yaw = poses[:, :2, 3], np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    keep = np.ones(len(pos0), bool)
    for a in range(0, len(pos0), 256):
        p = pos0[a:a + 256, None, :] + vel[a:a + 256, None, :] * times[None, :, None] - ego_xy[None]  # (m, T, 2)
        c, s_ = np.cos(ego_yaw)[None], np.sin(ego_yaw)[None]
        xe = c * p[..., 0] + s_ * p[..., 1]
        ye = -s_ * p[..., 0] + c * p[..., 1]
        rel = yaw[a:a + 256, None] - ego_yaw[None]
        w2, l2 = size[a:a + 256, 0:1] / 2, size[a:a + 256, 1:2] / 2
        lon = np.abs(np.cos(rel)) * l2 + np.abs(np.sin(rel)) * w2
        lat = np.abs(np.sin(rel)) * l2 + np.abs(np.cos(rel)) * w2
        hit = (np.abs(xe - 1.4) < 2.4 + lon + 0.4) & (np.abs(ye) < 1.0 + lat + 0.4)
        keep[a:a + 256] = ~hit.any(axis=1)
    if not keep.all():
        new_index = np.cumsum(keep) - 1
        pk = keep[parts.obj]
        parts = parts.subset(pk)
        parts.obj = new_index[parts.obj].astype(np.int32)
        world.parts = parts
        world.obj_pos0, world.obj_vel, world.obj_yaw, world.obj_size = pos0[keep], vel[keep], yaw[keep], size[keep]
        world.obj_category = [c for c, k in zip(b.obj_cat, keep) if k]
    return world
