"""The procedural city of one scene: roads, blocks, scenery, movable objects and the ego route.

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
road (bus stop, road works, truck + trailer, motorcycles, bicycles, bins ...) so that every class
appears near the ego in every scene. The ego drives the inner lane of the road y = 0 in +x at a
constant speed and may turn at one intersection.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ago_runtime.classes import OCC3D_ID as C

from .config import SynthConfig
from .raycast import BOX, CONE, CYL, ELL, MAP_CLASS, PrimitiveSet

# ---- surface codes of the ground raster, and their Occ3D class --------------------------------
S_ROAD, S_PARKING, S_SIDEWALK, S_GRASS, S_SOIL, S_ISLAND, S_WATER, S_RAIL, S_PLAZA, S_GRAVEL = range(10)
SURFACE_CLASS = np.array([C["driveable_surface"], C["driveable_surface"], C["sidewalk"], C["terrain"], C["terrain"],
                          C["other_flat"], C["other_flat"], C["other_flat"], C["sidewalk"], C["terrain"]], np.uint8)
# ---- materials (texture kinds, see render.py) ----------------------------------------------------
(M_GROUND, M_BUILDING, M_WALL, M_BODY, M_CABIN, M_TIRE, M_FOLIAGE, M_BARK, M_PERSON, M_SKIN, M_METAL, M_SIGN,
 M_TLIGHT, M_CONE, M_BARRIER, M_CONCRETE, M_PLASTIC, M_BUS) = range(18)

SLAB_HEIGHT = 0.15
RASTER_RES = 0.25  # metres per surface-raster cell


@dataclass
class Road:
    axis: int            # 0: runs along x (at y = pos), 1: runs along y (at x = pos)
    pos: float
    lanes: int           # per direction
    lane_w: float
    park_w: float        # parking strip width per side (0 = none)
    strip: int           # centre strip: 0 painted line, 1 raised island, 2 tram rail
    strip_w: float

    @property
    def half_width(self) -> float:
        return self.strip_w / 2 + self.lanes * self.lane_w + self.park_w

    def point(self, s, q) -> np.ndarray:
        """World xy of along-road coordinate s and lateral coordinate q (q > 0 = left of +axis)."""
        s, q = np.asarray(s, float), np.asarray(q, float)
        if self.axis == 0:
            return np.stack([s, self.pos + q], axis=-1)
        return np.stack([self.pos - q, s], axis=-1)

    @property
    def yaw(self) -> float:
        return 0.0 if self.axis == 0 else np.pi / 2

    def lane_q(self, k: int, forward: bool) -> float:
        q = self.strip_w / 2 + (k + 0.5) * self.lane_w
        return -q if forward else q


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


# ==================================================================================================
# builder
# ==================================================================================================

BUILDING_COLORS = np.array([[0.55, 0.28, 0.22], [0.80, 0.72, 0.58], [0.62, 0.62, 0.64], [0.86, 0.85, 0.80],
                            [0.38, 0.38, 0.42], [0.45, 0.55, 0.62], [0.70, 0.55, 0.40], [0.75, 0.78, 0.72]])
CAR_COLORS = np.array([[0.9, 0.9, 0.9], [0.1, 0.1, 0.12], [0.55, 0.56, 0.6], [0.7, 0.1, 0.1], [0.1, 0.2, 0.55],
                       [0.75, 0.75, 0.78], [0.25, 0.35, 0.3], [0.85, 0.75, 0.2], [0.4, 0.25, 0.15], [0.3, 0.3, 0.32]])
CLOTH_COLORS = np.array([[0.1, 0.1, 0.12], [0.2, 0.25, 0.45], [0.6, 0.1, 0.1], [0.85, 0.85, 0.8], [0.3, 0.4, 0.25],
                         [0.5, 0.45, 0.35], [0.9, 0.6, 0.1], [0.4, 0.4, 0.42]])


class _Builder:
    def __init__(self, config: SynthConfig, rng: np.random.Generator, half_size: float):
        self.cfg = config
        self.rng = rng
        self.static_rows: list[tuple] = []
        self.part_rows: list[tuple] = []
        self.obj_pos0: list = []
        self.obj_vel: list = []
        self.obj_yaw: list = []
        self.obj_size: list = []
        self.obj_cat: list = []
        half = half_size + 20.0
        self.origin = (-half, -half)
        n = int(np.ceil(2 * half / RASTER_RES))
        self.surface = np.full((n, n), S_GRASS, np.uint8)
        self.marking = np.zeros((n, n), np.uint8)
        self.half = half_size

    # ---- raster painting ---------------------------------------------------------------------
    def _cells(self, x0, x1, y0, y1):
        c0 = int(np.clip(np.floor((min(x0, x1) - self.origin[0]) / RASTER_RES), 0, self.surface.shape[1]))
        c1 = int(np.clip(np.ceil((max(x0, x1) - self.origin[0]) / RASTER_RES), 0, self.surface.shape[1]))
        r0 = int(np.clip(np.floor((min(y0, y1) - self.origin[1]) / RASTER_RES), 0, self.surface.shape[0]))
        r1 = int(np.clip(np.ceil((max(y0, y1) - self.origin[1]) / RASTER_RES), 0, self.surface.shape[0]))
        return r0, r1, c0, c1

    def paint(self, x0, x1, y0, y1, code, layer=None):
        r0, r1, c0, c1 = self._cells(x0, x1, y0, y1)
        (self.surface if layer is None else layer)[r0:r1, c0:c1] = code

    def paint_ellipse(self, cx, cy, rx, ry, code):
        r0, r1, c0, c1 = self._cells(cx - rx, cx + rx, cy - ry, cy + ry)
        ys = self.origin[1] + (np.arange(r0, r1) + 0.5) * RASTER_RES
        xs = self.origin[0] + (np.arange(c0, c1) + 0.5) * RASTER_RES
        inside = ((xs[None, :] - cx) / rx) ** 2 + ((ys[:, None] - cy) / ry) ** 2 <= 1
        self.surface[r0:r1, c0:c1][inside] = code

    # ---- primitives ----------------------------------------------------------------------------
    def static(self, kind, center, half, yaw, cls, mat, color, param=0.0):
        self.static_rows.append((kind, tuple(center), tuple(half), float(yaw), cls, mat, tuple(color), float(param), -1))

    def obj(self, category, xy, yaw, size, parts, velocity=(0.0, 0.0)) -> int:
        """Add a movable object: `parts` rows (kind, center_local_with_z_from_ground, half, yaw, cls, mat, color, param)."""
        idx = len(self.obj_cat)
        h = size[2]
        for kind, c, hf, y, cls, mat, color, param in parts:
            self.part_rows.append((kind, (c[0], c[1], c[2] - h / 2), tuple(hf), float(y), cls, mat, tuple(color),
                                   float(param), idx))
        self.obj_cat.append(category)
        self.obj_pos0.append(tuple(xy))
        self.obj_vel.append(tuple(velocity))
        self.obj_yaw.append(float(yaw))
        self.obj_size.append(tuple(size))
        return idx

    def jitter(self, color, amount=0.08):
        return np.clip(np.asarray(color) * self.rng.uniform(1 - amount, 1 + amount, 3), 0, 1)


# ---- object templates (parts in the object frame: x forward, y left, z from the ground) ----------

def _wheels(l, w, r=0.33, width=0.22):
    rows = []
    for sx in (0.34, -0.34):
        for sy in (1, -1):
            rows.append((BOX, (sx * l, sy * (w / 2 - width / 2 + 0.02), r), (r, width / 2, r), 0.0, None, M_TIRE,
                         (0.06, 0.06, 0.06), 0.0))
    return rows


def make_vehicle(b: _Builder, category: str):
    """(size wlh, parts) of a vehicle of nuScenes `category`, with this instance's colours."""
    rng = b.rng
    if category == "vehicle.car":
        l, w = rng.uniform(3.9, 4.9), rng.uniform(1.72, 1.95)
        h = rng.uniform(1.42, 1.62) if rng.random() < 0.7 else rng.uniform(1.7, 2.0)
        color = b.jitter(CAR_COLORS[rng.integers(len(CAR_COLORS))])
        body_top = 0.58 * h
        parts = [(BOX, (0, 0, (0.22 + body_top) / 2), (l / 2, w / 2, (body_top - 0.22) / 2), 0.0, None, M_BODY, color, 0.0),
                 (BOX, (-0.06 * l, 0, (body_top + h) / 2), (0.29 * l, 0.45 * w, (h - body_top) / 2), 0.0, None, M_CABIN,
                  color, 0.0)] + _wheels(l, w)
        cls = C["car"]
    elif category == "vehicle.truck":
        cab_l, l, w = 2.3, rng.uniform(6.5, 9.5), 2.45
        h = rng.uniform(3.0, 3.8)
        color = b.jitter(CAR_COLORS[rng.integers(len(CAR_COLORS))])
        cargo = b.jitter([0.85, 0.85, 0.85] if rng.random() < 0.6 else [0.6, 0.2, 0.1])
        parts = [(BOX, (l / 2 - cab_l / 2, 0, 1.65), (cab_l / 2, w / 2, 1.3), 0.0, None, M_BODY, color, 0.0),
                 (BOX, (l / 2 - cab_l / 2, 0, 2.65), (cab_l / 2 - 0.05, w / 2 - 0.05, 0.3), 0.0, None, M_CABIN, color, 0.0),
                 (BOX, (-cab_l / 2 - 0.1, 0, (0.9 + h) / 2), ((l - cab_l - 0.2) / 2, w / 2, (h - 0.9) / 2), 0.0, None,
                  M_PLASTIC, cargo, 1.0)] + _wheels(l, w, 0.48, 0.3)
        cls = C["truck"]
    elif category == "vehicle.bus.rigid":
        l, w, h = rng.uniform(10.5, 12.5), 2.55, rng.uniform(3.0, 3.4)
        color = b.jitter([[0.85, 0.15, 0.1], [0.1, 0.3, 0.7], [0.9, 0.9, 0.85], [0.2, 0.55, 0.3]][rng.integers(4)])
        parts = [(BOX, (0, 0, (0.35 + h) / 2), (l / 2, w / 2, (h - 0.35) / 2), 0.0, None, M_BUS, color, 0.0)] + \
            _wheels(l, w, 0.5, 0.3)
        cls = C["bus"]
    elif category == "vehicle.trailer":
        l, w, h = rng.uniform(8.0, 12.0), 2.5, rng.uniform(3.4, 3.9)
        color = b.jitter([[0.85, 0.85, 0.85], [0.7, 0.5, 0.2], [0.3, 0.4, 0.6], [0.6, 0.15, 0.1]][rng.integers(4)])
        parts = [(BOX, (0, 0, (1.1 + h) / 2), (l / 2, w / 2, (h - 1.1) / 2), 0.0, None, M_PLASTIC, color, 1.0),
                 (BOX, (0.35 * l, 0, 0.55), (0.1, w / 2 - 0.3, 0.55), 0.0, None, M_METAL, (0.3, 0.3, 0.3), 0.0),
                 (BOX, (-0.35 * l, 0, 0.5), (0.9, w / 2, 0.5), 0.0, None, M_TIRE, (0.06, 0.06, 0.06), 0.0)]
        cls = C["trailer"]
    elif category == "vehicle.construction":
        l, w, h = rng.uniform(6.0, 8.0), 2.8, rng.uniform(3.0, 3.6)
        yellow = b.jitter([0.95, 0.72, 0.1])
        parts = [(BOX, (-0.1 * l, 0, 0.45), (0.3 * l, w / 2, 0.45), 0.0, None, M_TIRE, (0.08, 0.08, 0.08), 0.0),
                 (BOX, (-0.12 * l, 0, 1.5), (1.4, 1.3, 0.6), 0.0, None, M_BODY, yellow, 0.0),
                 (BOX, (-0.05 * l, 0.5, 2.5), (0.7, 0.6, 0.55), 0.0, None, M_CABIN, yellow, 0.0),
                 (BOX, (0.25 * l, -0.3, 2.2), (0.25 * l, 0.2, 0.2), -0.0, None, M_BODY, yellow, 0.0),
                 (BOX, (0.47 * l, -0.3, 1.0), (0.2, 0.25, 1.0), 0.0, None, M_BODY, yellow, 0.0)]
        cls = C["construction_vehicle"]
    elif category == "vehicle.motorcycle":
        l, w, h = rng.uniform(1.9, 2.3), 0.8, rng.uniform(1.2, 1.5)
        color = b.jitter(CAR_COLORS[rng.integers(len(CAR_COLORS))])
        parts = [(BOX, (0, 0, 0.65), (l / 2 - 0.35, 0.18, 0.25), 0.0, None, M_BODY, color, 0.0),
                 (BOX, (l / 2 - 0.33, 0, 0.33), (0.33, 0.06, 0.33), 0.0, None, M_TIRE, (0.06, 0.06, 0.06), 0.0),
                 (BOX, (-l / 2 + 0.33, 0, 0.33), (0.33, 0.07, 0.33), 0.0, None, M_TIRE, (0.06, 0.06, 0.06), 0.0),
                 (BOX, (l / 2 - 0.5, 0, 0.95), (0.06, 0.38, 0.05), 0.0, None, M_METAL, (0.2, 0.2, 0.2), 0.0)]
        cls = C["motorcycle"]
    elif category == "vehicle.bicycle":
        l, w, h = rng.uniform(1.6, 1.8), 0.6, 1.1
        color = b.jitter(CAR_COLORS[rng.integers(len(CAR_COLORS))])
        parts = [(BOX, (0, 0, 0.65), (0.45, 0.05, 0.22), 0.0, None, M_METAL, color, 0.0),
                 (BOX, (l / 2 - 0.34, 0, 0.34), (0.34, 0.04, 0.34), 0.0, None, M_TIRE, (0.08, 0.08, 0.08), 0.0),
                 (BOX, (-l / 2 + 0.34, 0, 0.34), (0.34, 0.04, 0.34), 0.0, None, M_TIRE, (0.08, 0.08, 0.08), 0.0),
                 (BOX, (l / 2 - 0.45, 0, 1.0), (0.05, 0.28, 0.04), 0.0, None, M_METAL, (0.15, 0.15, 0.15), 0.0)]
        cls = C["bicycle"]
    else:
        raise ValueError(category)
    parts = [(k, c, hf, y, cls if pc is None else pc, m, col, p) for k, c, hf, y, pc, m, col, p in parts]
    return (w, l, h), parts


def add_rider(b: _Builder, parts, size, cls):
    """A person sitting on a bicycle/motorcycle (labelled as the vehicle, as in nuScenes lidarseg boxes)."""
    cloth = b.jitter(CLOTH_COLORS[b.rng.integers(len(CLOTH_COLORS))])
    parts.append((CYL, (-0.1, 0, 1.25), (0.2, 0.2, 0.35), 0.0, cls, M_PERSON, cloth, 0.0))
    parts.append((ELL, (-0.05, 0, 1.72), (0.11, 0.1, 0.13), 0.0, cls, M_SKIN, b.jitter([0.75, 0.58, 0.45], 0.25), 0.0))
    return (size[0], size[1], 1.85)


def make_pedestrian(b: _Builder):
    rng = b.rng
    h = rng.uniform(1.55, 1.9)
    shirt = b.jitter(CLOTH_COLORS[rng.integers(len(CLOTH_COLORS))], 0.2)
    r = rng.uniform(0.18, 0.24)
    body_h = h - 0.24
    parts = [(CYL, (0, 0, body_h / 2), (r, r, body_h / 2), 0.0, C["pedestrian"], M_PERSON, shirt,
              float(rng.integers(len(CLOTH_COLORS)))),
             (ELL, (0, 0, h - 0.12), (0.1, 0.09, 0.12), 0.0, C["pedestrian"], M_SKIN,
              b.jitter([0.75, 0.58, 0.45], 0.3), 0.0)]
    return (0.6, 0.6, h), parts


def make_small(b: _Builder, what: str):
    """Cones, barriers, bins, strollers, debris: (category, size, parts)."""
    rng = b.rng
    if what == "cone":
        h = rng.uniform(0.5, 0.8)
        return "movable_object.trafficcone", (0.4, 0.4, h), [
            (CONE, (0, 0, h / 2 + 0.02), (0.17, 0.17, h / 2 - 0.02), 0.0, C["traffic_cone"], M_CONE, (0.95, 0.35, 0.05), 0.0),
            (BOX, (0, 0, 0.02), (0.2, 0.2, 0.02), 0.0, C["traffic_cone"], M_PLASTIC, (0.1, 0.1, 0.1), 0.0)]
    if what == "barrier":
        h = rng.uniform(0.8, 1.1)
        concrete = rng.random() < 0.5
        color = (0.7, 0.7, 0.68) if concrete else (0.9, 0.15, 0.1)
        return "movable_object.barrier", (0.5, 2.0, h), [
            (BOX, (0, 0, h / 2), (1.0, 0.22 if concrete else 0.08, h / 2), 0.0, C["barrier"],
             M_CONCRETE if concrete else M_BARRIER, b.jitter(color), 0.0)]
    if what == "bin":
        color = b.jitter([[0.15, 0.4, 0.2], [0.3, 0.3, 0.32], [0.1, 0.25, 0.6], [0.55, 0.35, 0.1]][rng.integers(4)])
        return "movable_object.pushable_pullable", (0.6, 0.7, 1.05), [
            (BOX, (0, 0, 0.52), (0.35, 0.3, 0.52), 0.0, C["others"], M_PLASTIC, color, 0.0)]
    if what == "stroller":
        return "human.pedestrian.stroller", (0.6, 0.9, 1.0), [
            (BOX, (0, 0, 0.6), (0.4, 0.28, 0.3), 0.0, C["others"], M_PLASTIC, b.jitter([0.2, 0.2, 0.5]), 0.0),
            (BOX, (0, 0, 0.15), (0.4, 0.25, 0.15), 0.0, C["others"], M_TIRE, (0.1, 0.1, 0.1), 0.0)]
    if what == "debris":
        s = rng.uniform(0.8, 2.0)
        return "movable_object.debris", (s, s * 1.3, s * 0.6), [
            (ELL, (0, 0, 0.0), (s * 0.6, s * 0.7, s * 0.6), 0.0, C["others"], M_PLASTIC, b.jitter([0.45, 0.38, 0.3]), 0.0)]
    raise ValueError(what)


# ---- scenery templates ----------------------------------------------------------------------------

def add_tree(b: _Builder, x, y, z0=SLAB_HEIGHT, scale=1.0):
    rng = b.rng
    trunk_h = rng.uniform(1.8, 3.2) * scale
    tr = rng.uniform(0.12, 0.25) * scale
    leaf = b.jitter([[0.2, 0.42, 0.15], [0.28, 0.5, 0.2], [0.15, 0.33, 0.12], [0.35, 0.45, 0.18]][rng.integers(4)], 0.12)
    b.static(CYL, (x, y, z0 + trunk_h / 2 + 0.3), (tr, tr, trunk_h / 2 + 0.3), 0, C["vegetation"], M_BARK,
             b.jitter([0.35, 0.26, 0.18]))
    if rng.random() < 0.75:
        rx, rz = rng.uniform(1.4, 3.2) * scale, rng.uniform(1.5, 3.0) * scale
        b.static(ELL, (x, y, z0 + trunk_h + rz * 0.85), (rx, rx * rng.uniform(0.85, 1.15), rz), rng.uniform(0, np.pi),
                 C["vegetation"], M_FOLIAGE, leaf, rng.uniform(0, 100))
    else:  # conifer
        r, hh = rng.uniform(1.2, 2.2) * scale, rng.uniform(3.0, 6.0) * scale
        b.static(CONE, (x, y, z0 + trunk_h * 0.5 + hh / 2), (r, r, hh / 2), 0, C["vegetation"], M_FOLIAGE,
                 leaf * 0.8, rng.uniform(0, 100))


def add_bush(b: _Builder, x, y, z0=SLAB_HEIGHT):
    r = b.rng.uniform(0.5, 1.3)
    b.static(ELL, (x, y, z0 + r * 0.55), (r * b.rng.uniform(1.0, 1.8), r, r * 0.75), b.rng.uniform(0, np.pi),
             C["vegetation"], M_FOLIAGE, b.jitter([0.22, 0.4, 0.16], 0.15), b.rng.uniform(0, 100))


def add_street_light(b: _Builder, x, y, facing_yaw):
    h = b.rng.uniform(6.5, 9.0)
    grey = b.jitter([0.45, 0.47, 0.5])
    b.static(CYL, (x, y, SLAB_HEIGHT + h / 2), (0.1, 0.1, h / 2), 0, C["manmade"], M_METAL, grey)
    dx, dy = np.cos(facing_yaw), np.sin(facing_yaw)
    b.static(BOX, (x + dx * 0.9, y + dy * 0.9, SLAB_HEIGHT + h - 0.1), (0.9, 0.07, 0.07), facing_yaw, C["manmade"], M_METAL, grey)
    b.static(BOX, (x + dx * 1.7, y + dy * 1.7, SLAB_HEIGHT + h - 0.2), (0.35, 0.15, 0.08), facing_yaw, C["manmade"], M_METAL,
             (0.8, 0.8, 0.75))


def add_sign(b: _Builder, x, y, facing_yaw):
    h = b.rng.uniform(2.2, 2.8)
    b.static(CYL, (x, y, SLAB_HEIGHT + h / 2), (0.04, 0.04, h / 2), 0, C["manmade"], M_METAL, (0.55, 0.55, 0.57))
    color = [[0.8, 0.1, 0.1], [0.1, 0.3, 0.75], [0.95, 0.95, 0.95], [0.95, 0.8, 0.1]][b.rng.integers(4)]
    b.static(BOX, (x, y, SLAB_HEIGHT + h + 0.3), (0.03, 0.35, 0.35), facing_yaw, C["manmade"], M_SIGN, color,
             b.rng.integers(3))


def add_traffic_light(b: _Builder, x, y, facing_yaw):
    h = b.rng.uniform(3.6, 4.4)
    b.static(CYL, (x, y, SLAB_HEIGHT + h / 2), (0.09, 0.09, h / 2), 0, C["manmade"], M_METAL, (0.3, 0.3, 0.32))
    b.static(BOX, (x, y, SLAB_HEIGHT + h + 0.5), (0.18, 0.2, 0.5), facing_yaw, C["manmade"], M_TLIGHT, (0.12, 0.12, 0.12),
             b.rng.integers(3))


def add_building(b: _Builder, cx, cy, yaw, width, depth, height):
    """width along the facade (local y), depth away from the street (local x)."""
    color = b.jitter(BUILDING_COLORS[b.rng.integers(len(BUILDING_COLORS))], 0.1)
    spacing = b.rng.uniform(2.2, 3.8) if b.rng.random() < 0.85 else 0.0
    b.static(BOX, (cx, cy, SLAB_HEIGHT + height / 2), (depth / 2, width / 2, height / 2), yaw, C["manmade"], M_BUILDING,
             color, spacing)
    if b.rng.random() < 0.3:  # rooftop structure
        b.static(BOX, (cx, cy, SLAB_HEIGHT + height + 1.0), (depth / 5, width / 5, 1.0), yaw, C["manmade"], M_WALL,
                 color * 0.9)


# ==================================================================================================

def _positions(rng, start, lo, hi, half):
    """Road centre positions: `start`, then steps of U(lo, hi) both ways until |pos| > half."""
    out = [start]
    while out[-1] < half:
        out.append(out[-1] + rng.uniform(lo, hi))
    p = start
    while p > -half:
        p -= rng.uniform(lo, hi)
        out.insert(0, p)
    return out


def _make_road(rng, axis, pos, ego=False) -> Road:
    lanes = 2 if rng.random() < 0.6 else 1
    lane_w = rng.uniform(3.2, 3.7)
    park_w = 2.4 if (ego or rng.random() < 0.6) else 0.0
    strip = int(rng.choice([0, 1, 2], p=[0.5, 0.35, 0.15]))
    if ego and strip == 0:
        strip = 1 if rng.random() < 0.7 else 2
    strip_w = {0: 0.3, 1: rng.uniform(1.2, 2.4), 2: 2.8}[strip]
    return Road(axis, pos, lanes, lane_w, park_w, strip, strip_w)


def build_world(config: SynthConfig, scene_index: int) -> World:
    rng = np.random.default_rng([config.seed, scene_index, 7])
    duration = (config.frames_per_scene - 1) * config.keyframe_interval_s
    speed = rng.uniform(config.ego_speed_min, config.ego_speed_max)
    travel = speed * duration
    half = max(config.world_size / 2, travel + 80.0)  # long scenes get a bigger city
    b = _Builder(config, rng, half)
    x_start = -min(travel / 2, 60.0)

    # ---- roads ----------------------------------------------------------------------------------
    ys = _positions(rng, 0.0, config.block_min, config.block_max, half)
    # the ego starts in a long block (room for the points of interest), the next crossing ~40 m ahead
    first = x_start + rng.uniform(36, 48)
    gap = rng.uniform(78, 95)
    xs = sorted([p for p in _positions(rng, first, config.block_min, config.block_max, half) if p >= first]
                + [p for p in _positions(rng, first - gap, config.block_min, config.block_max, half) if p <= first - gap])
    xroads = [_make_road(rng, 0, y, ego=(y == 0.0)) for y in ys]
    yroads = [_make_road(rng, 1, x) for x in xs]
    ego_road = xroads[ys.index(0.0)]
    roads = xroads + yroads

    # ---- ego route: inner forward lane of the road y = 0, maybe one turn ---------------------------
    q0 = ego_road.lane_q(0, True)
    route = [np.array([x_start - 40.0, q0]), np.array([x_start, q0])]
    turn = rng.random() < 0.5
    cross = [r for r in yroads if r.pos > x_start + 15.0 + travel * 0.2]
    if turn and cross and cross[0].pos < x_start + travel - 10:
        rb = cross[0]
        left = rng.random() < 0.5
        b_off = rb.strip_w / 2 + rb.lane_w / 2
        R = 6.0 + (abs(q0) + b_off if left else 0.0)
        if left:
            cx, cy, sign = rb.pos + b_off - R, q0 + R, 1
        else:
            cx, cy, sign = rb.pos - b_off - R, q0 - R, -1
        ang = np.linspace(0, np.pi / 2, 40)
        arc = np.stack([cx + R * np.sin(ang), cy - sign * R * np.cos(ang)], 1)
        route = [route[0], np.array([cx, q0])] + list(arc[1:])
        route.append(route[-1] + np.array([0, sign * (travel + 60.0)]))
    else:
        route.append(np.array([x_start + travel + 60.0, q0]))
    pts = [route[0]]
    for p in route[1:]:
        seg = np.linspace(pts[-1], p, max(2, int(np.linalg.norm(p - pts[-1]) / 0.1) + 1))[1:]
        pts.extend(seg)
    route_xy = np.array(pts)
    route_s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(route_xy, axis=0), axis=1))])
    ego_s0 = 40.0

    # ---- surface raster: roads, strips, markings -------------------------------------------------
    ext = half + 20
    for r in roads:
        hw = r.half_width
        lo, hi = (-ext, ext)
        if r.axis == 0:
            b.paint(lo, hi, r.pos - hw, r.pos + hw, S_ROAD)
        else:
            b.paint(r.pos - hw, r.pos + hw, lo, hi, S_ROAD)
    for r in roads:  # parking strips, then strips/markings between intersections
        others = yroads if r.axis == 0 else xroads
        cuts = sorted((o.pos - o.half_width, o.pos + o.half_width) for o in others)
        spans, s = [], -ext
        for a, c in cuts:
            if a > s:
                spans.append((s, a))
            s = max(s, c)
        spans.append((s, ext))
        hw = r.half_width
        for s0, s1 in spans:
            def rect(q0_, q1_, code, layer=None):
                p0, p1 = r.point(s0, q0_), r.point(s1, q1_)
                b.paint(p0[0], p1[0], p0[1], p1[1], code, layer)
            if r.park_w:
                rect(hw - r.park_w, hw, S_PARKING)
                rect(-hw, -hw + r.park_w, S_PARKING)
            edge = hw - r.park_w
            # lane lines
            rect(edge - 0.25, edge - 0.1, 1, b.marking)
            rect(-edge + 0.1, -edge + 0.25, 1, b.marking)
            if r.strip == 0:
                rect(-0.15, -0.05, 2, b.marking)
                rect(0.05, 0.15, 2, b.marking)
            elif s1 - s0 > 6:
                code = S_ISLAND if r.strip == 1 else S_RAIL
                sa, sb = s0 + 2.5, s1 - 2.5
                p0, p1 = r.point(sa, -r.strip_w / 2), r.point(sb, r.strip_w / 2)
                b.paint(p0[0], p1[0], p0[1], p1[1], code)
                if r.strip == 1:
                    c = (p0 + p1) / 2
                    e = np.abs(p1 - p0) / 2
                    b.static(BOX, (c[0], c[1], SLAB_HEIGHT / 2), (e[0], e[1], SLAB_HEIGHT / 2), 0, MAP_CLASS, M_GROUND,
                             (1, 1, 1))
            if r.lanes == 2:  # dashed lines between the two lanes of each direction
                for q in (r.strip_w / 2 + r.lane_w, -(r.strip_w / 2 + r.lane_w)):
                    for d0 in np.arange(s0 + 2, s1 - 3, 9.0):
                        p0, p1 = r.point(d0, q - 0.07), r.point(d0 + 3.0, q + 0.07)
                        b.paint(p0[0], p1[0], p0[1], p1[1], 1, b.marking)
            # zebra crossings at both ends of the span
            for end, sgn in ((s0, 1), (s1, -1)):
                if abs(end) >= ext - 1:
                    continue
                for q in np.arange(-edge + 0.3, edge - 0.3, 1.0):
                    p0, p1 = r.point(end + sgn * 1.0, q), r.point(end + sgn * 4.0, q + 0.5)
                    b.paint(p0[0], p1[0], p0[1], p1[1], 1, b.marking)
                p0, p1 = r.point(end + sgn * 5.0, 0), r.point(end + sgn * 5.4, -edge if sgn > 0 else edge)
                b.paint(p0[0], p1[0], p0[1], p1[1], 1, b.marking)

    # ---- blocks ------------------------------------------------------------------------------------
    block_types = ["urban"] * 12 + ["park"] * 3 + ["parking"] * 2 + ["construction"] * 3
    for i in range(len(xroads) - 1):
        for j in range(len(yroads) - 1):
            y0 = xroads[i].pos + xroads[i].half_width
            y1 = xroads[i + 1].pos - xroads[i + 1].half_width
            x0 = yroads[j].pos + yroads[j].half_width
            x1 = yroads[j + 1].pos - yroads[j + 1].half_width
            if x1 - x0 < 12 or y1 - y0 < 12:
                continue
            if max(abs(x0), abs(x1)) > half + 40 or max(abs(y0), abs(y1)) > half + 40:
                continue
            near_ego = (y0 < 30 and y1 > -30) and (x1 > x_start - 20 and x0 < x_start + 60)
            kind = block_types[rng.integers(len(block_types))]
            if near_ego and (kind == "parking" or (kind == "park" and rng.random() < 0.5)):
                kind = "urban"
            _block(b, x0, x1, y0, y1, kind)

    # ---- parked vehicles, traffic, pedestrians ----------------------------------------------------
    for r in roads:
        others = yroads if r.axis == 0 else xroads
        cuts = sorted((o.pos - o.half_width - 6.0, o.pos + o.half_width + 6.0) for o in others)

        def clear(s_):
            return all(not (a < s_ < c) for a, c in cuts)

        hw = r.half_width
        if r.park_w:
            for side in (1, -1):
                s = -half + rng.uniform(0, 8)
                while s < half:
                    if rng.random() < config.parked_fill and clear(s) and not (r is ego_road and abs(s - x_start) < 45):
                        cat = rng.choice(["vehicle.car", "vehicle.truck", "vehicle.motorcycle", "vehicle.bus.rigid",
                                          "vehicle.trailer"], p=[0.86, 0.05, 0.04, 0.02, 0.03])
                        size, parts = make_vehicle(b, str(cat))
                        if clear(s + size[1]):
                            xy = r.point(s + size[1] / 2, side * (hw - r.park_w / 2))
                            b.obj(str(cat), xy, r.yaw + (0 if rng.random() < 0.5 else np.pi), size, parts)
                            s += size[1]
                    s += rng.uniform(1.0, 6.0)
        # moving vehicles
        length = 2 * half
        for forward in (True, False):
            for k in range(r.lanes):
                n = rng.poisson(config.moving_vehicles_per_100m_lane * length / 100)
                q = r.lane_q(k, forward)
                for s in rng.uniform(-half, half, n):
                    cat = str(rng.choice(["vehicle.car", "vehicle.truck", "vehicle.bus.rigid", "vehicle.motorcycle",
                                          "vehicle.bicycle"], p=[0.8, 0.07, 0.05, 0.04, 0.04]))
                    size, parts = make_vehicle(b, cat)
                    v = rng.uniform(5.0, 11.0)
                    qq = q
                    if cat in ("vehicle.motorcycle", "vehicle.bicycle"):
                        size = add_rider(b, parts, size, C["motorcycle" if cat == "vehicle.motorcycle" else "bicycle"])
                        if cat == "vehicle.bicycle":
                            v = rng.uniform(3.0, 5.5)
                            qq = q + (1 if q > 0 else -1) * (r.lane_w / 2 - 0.6) if k == r.lanes - 1 else q
                    a = np.array([1.0, 0.0]) if r.axis == 0 else np.array([0.0, 1.0])
                    d = a if forward else -a
                    b.obj(cat, r.point(s, qq), np.arctan2(d[1], d[0]), size, parts, velocity=tuple(d * v))

    # ---- points of interest next to the ego road (every class near the ego) -------------------------
    _points_of_interest(b, ego_road, yroads, x_start, travel)

    # ---- pedestrians on zebra crossings near the route ---------------------------------------------
    for r in yroads:
        if not (x_start - 60 < r.pos < x_start + travel + 60):
            continue
        for side in (1, -1):
            for _ in range(rng.integers(0, 3)):
                edge = ego_road.half_width
                x = r.pos + side * (r.half_width + rng.uniform(1.5, 3.5))
                v = rng.uniform(0.9, 1.5) * (1 if rng.random() < 0.5 else -1)
                y = rng.uniform(-edge, edge)
                size, parts = make_pedestrian(b)
                b.obj("human.pedestrian.adult", (x, y), np.pi / 2 if v > 0 else -np.pi / 2, size, parts,
                      velocity=(0.0, v))

    world = _finish(b, config, scene_index, route_xy, route_s, speed, ego_s0, roads)
    return world


def _sidewalk_walkers(b: _Builder, x0, x1, y0, y1, sw, verge=0.0):
    """Pedestrians walking along the sidewalk ring of a block (and a few standing)."""
    rng = b.rng
    per = 2 * ((x1 - x0) + (y1 - y0))
    n = rng.poisson(b.cfg.pedestrians_per_100m_sidewalk * per / 100)
    for _ in range(n):
        side = rng.integers(4)
        t = rng.uniform(0.05, 0.95)
        off = verge + rng.uniform(0.6, sw - 0.5)
        if side == 0:
            xy, axis = (x0 + t * (x1 - x0), y0 + off), 0
        elif side == 1:
            xy, axis = (x0 + t * (x1 - x0), y1 - off), 0
        elif side == 2:
            xy, axis = (x0 + off, y0 + t * (y1 - y0)), 1
        else:
            xy, axis = (x1 - off, y0 + t * (y1 - y0)), 1
        v = rng.uniform(0.8, 1.6) * (1 if rng.random() < 0.5 else -1) if rng.random() < 0.75 else 0.0
        vel = (v, 0.0) if axis == 0 else (0.0, v)
        yaw = np.arctan2(vel[1], vel[0]) if v else rng.uniform(-np.pi, np.pi)
        size, parts = make_pedestrian(b)
        parts = _raised(parts)
        b.obj("human.pedestrian.adult", xy, yaw, (size[0], size[1], size[2] + SLAB_HEIGHT), parts, velocity=vel)
        if rng.random() < 0.06:  # a stroller or a cart pushed in front
            cat, ssize, sparts = make_small(b, "stroller")
            sparts = _raised(sparts)
            d = np.array([np.cos(yaw), np.sin(yaw)])
            b.obj(cat, tuple(np.asarray(xy) + 0.9 * d), yaw, (ssize[0], ssize[1], ssize[2] + SLAB_HEIGHT), sparts,
                  velocity=vel)


def _raised(parts):
    return [(k, (c[0], c[1], c[2] + SLAB_HEIGHT), h, y, cl, m, co, pa) for k, c, h, y, cl, m, co, pa in parts]


def _block(b: _Builder, x0, x1, y0, y1, kind):
    rng = b.rng

    def U(lo, hi):  # uniform that tolerates an empty range (small blocks)
        return rng.uniform(lo, max(lo, hi))

    sw = rng.uniform(2.5, 4.5)
    # slab (curb + block top), class from the raster
    b.static(BOX, ((x0 + x1) / 2, (y0 + y1) / 2, SLAB_HEIGHT / 2), ((x1 - x0) / 2, (y1 - y0) / 2, SLAB_HEIGHT / 2), 0,
             MAP_CLASS, M_GROUND, (1, 1, 1))
    # optional grass verge between the curb and the sidewalk (street trees stand in it)
    verge = rng.uniform(1.2, 2.8) if rng.random() < 0.35 else 0.0
    b.paint(x0, x1, y0, y1, S_GRASS)
    b.paint(x0 + verge, x1 - verge, y0 + verge, y1 - verge, S_SIDEWALK)
    ix0, ix1, iy0, iy1 = x0 + verge + sw, x1 - verge - sw, y0 + verge + sw, y1 - verge - sw
    inner = {"urban": S_PLAZA if rng.random() < 0.5 else S_GRASS, "park": S_GRASS, "parking": S_PARKING,
             "construction": S_SOIL}[kind]
    b.paint(ix0, ix1, iy0, iy1, inner)

    # street furniture along the curb, facing the road
    for side in range(4):
        if side < 2:
            a0, a1, fixed, axis = x0, x1, (y0 + 0.7 if side == 0 else y1 - 0.7), 0
            facing = -np.pi / 2 if side == 0 else np.pi / 2
        else:
            a0, a1, fixed, axis = y0, y1, (x0 + 0.7 if side == 2 else x1 - 0.7), 1
            facing = np.pi if side == 2 else 0.0
        def at(t):
            return (t, fixed) if axis == 0 else (fixed, t)
        # traffic lights at both corners
        add_traffic_light(b, *at(a0 + 1.0), facing)
        if rng.random() < 0.5:
            add_traffic_light(b, *at(a1 - 1.0), facing)
        t = a0 + rng.uniform(4, 12)
        while t < a1 - 4:
            add_street_light(b, *at(t), facing)
            t += rng.uniform(22, 32)
        t = a0 + rng.uniform(4, 9)
        tree_p = 0.75 if kind != "parking" else 0.4
        while t < a1 - 5:
            r = rng.random()
            if r < tree_p:
                add_tree(b, *at(t))
            elif r < tree_p + 0.06:
                add_sign(b, *at(t), facing)
            elif r < tree_p + 0.12:
                cat, size, parts = make_small(b, "bin")
                b.obj(cat, at(t), facing, (size[0], size[1], size[2] + SLAB_HEIGHT), _raised(parts))
            elif r < tree_p + 0.16:
                add_bush(b, *at(t))
            elif r < tree_p + 0.19:
                b.static(CYL, (*at(t), SLAB_HEIGHT + 0.35), (0.15, 0.15, 0.35), 0, C["others"], M_PLASTIC, (0.8, 0.1, 0.1))
            t += rng.uniform(5, 11)
    _sidewalk_walkers(b, x0, x1, y0, y1, sw, verge)

    if ix1 - ix0 < 6 or iy1 - iy0 < 6:
        return
    if kind == "urban":
        for side in range(4):
            # buildings along each inner edge; local x = depth (away from the street)
            if side < 2:
                a0, a1 = ix0, ix1
            else:
                a0, a1 = iy0 + 8, iy1 - 8
            t = a0
            max_depth = min(ix1 - ix0, iy1 - iy0) / 2 - 1
            while t < a1 - 4:
                width = min(rng.uniform(8, 26), a1 - t)
                depth = min(rng.uniform(8, 18), max_depth)
                setback = rng.uniform(0, 3) if rng.random() < 0.5 else 0.0
                height = rng.uniform(5, 28)
                if setback > 0.5:
                    code = S_PLAZA if rng.random() < 0.5 else S_GRASS
                    if side == 0:
                        b.paint(t, t + width, iy0, iy0 + setback, code)
                    elif side == 1:
                        b.paint(t, t + width, iy1 - setback, iy1, code)
                    elif side == 2:
                        b.paint(ix0, ix0 + setback, t, t + width, code)
                    else:
                        b.paint(ix1 - setback, ix1, t, t + width, code)
                c = t + width / 2
                dd = setback + depth / 2
                if rng.random() < 0.85:
                    if side == 0:
                        add_building(b, c, iy0 + dd, np.pi / 2, width, depth, height)
                    elif side == 1:
                        add_building(b, c, iy1 - dd, np.pi / 2, width, depth, height)
                    elif side == 2:
                        add_building(b, ix0 + dd, c, 0.0, width, depth, height)
                    else:
                        add_building(b, ix1 - dd, c, 0.0, width, depth, height)
                else:  # a wall or a hedge along the sidewalk, lawn behind
                    hedge = rng.random() < 0.5
                    hh = rng.uniform(1.0, 1.8) if hedge else rng.uniform(1.5, 2.6)
                    cls, mat = (C["vegetation"], M_FOLIAGE) if hedge else (C["manmade"], M_WALL)
                    col = b.jitter([0.2, 0.38, 0.15]) if hedge else b.jitter([0.65, 0.62, 0.58])
                    th = 0.5 if hedge else 0.25
                    if side < 2:
                        yy = iy0 + th if side == 0 else iy1 - th
                        b.static(BOX, (c, yy, SLAB_HEIGHT + hh / 2), (width / 2, th, hh / 2), 0, cls, mat, col, 7.0)
                    else:
                        xx = ix0 + th if side == 2 else ix1 - th
                        b.static(BOX, (xx, c, SLAB_HEIGHT + hh / 2), (th, width / 2, hh / 2), 0, cls, mat, col, 7.0)
                t += width + (rng.uniform(0, 5) if rng.random() < 0.4 else 0.0)
        # courtyard trees
        for _ in range(rng.integers(0, 4)):
            add_tree(b, U(ix0 + 20, max(ix0 + 20.1, ix1 - 20)), U(iy0 + 20, max(iy0 + 20.1, iy1 - 20)))
    elif kind == "park":
        for _ in range(rng.integers(2, 6)):
            b.paint_ellipse(U(ix0, ix1), U(iy0, iy1), rng.uniform(3, 10), rng.uniform(3, 10), S_SOIL)
        cy = U(iy0, iy1)
        b.paint(ix0, ix1, cy - 1.2, cy + 1.2, S_PLAZA)  # a path
        if rng.random() < 0.6:
            b.paint_ellipse((ix0 + ix1) / 2, (iy0 + iy1) / 2, (ix1 - ix0) / 5, (iy1 - iy0) / 6, S_WATER)
        area = (ix1 - ix0) * (iy1 - iy0)
        for _ in range(int(area / 90)):
            x, y = U(ix0 + 1, ix1 - 1), U(iy0 + 1, iy1 - 1)
            r0, _, c0, _ = b._cells(x, x, y, y)
            if b.surface[min(r0, b.surface.shape[0] - 1), min(c0, b.surface.shape[1] - 1)] == S_WATER:
                continue
            (add_tree if rng.random() < 0.6 else add_bush)(b, x, y)
        for _ in range(rng.integers(1, 4)):
            cat, size, parts = make_small(b, "bin")
            b.obj(cat, (U(ix0, ix1), cy + 1.6), 0.0, (size[0], size[1], size[2] + SLAB_HEIGHT), _raised(parts))
    elif kind == "parking":
        for row_y in np.arange(iy0 + 3, iy1 - 3, 6.5):
            for x in np.arange(ix0 + 2, ix1 - 2, 2.8):
                if rng.random() < 0.6:
                    cat = str(rng.choice(["vehicle.car", "vehicle.truck", "vehicle.trailer"], p=[0.88, 0.07, 0.05]))
                    size, parts = make_vehicle(b, cat)
                    if cat != "vehicle.car":
                        continue
                    b.obj(cat, (x, row_y), np.pi / 2 + (np.pi if rng.random() < 0.5 else 0), (size[0], size[1], size[2] + SLAB_HEIGHT),
                          _raised(parts))
        for x in np.arange(ix0 + 3, ix1 - 3, 20.0):
            add_street_light(b, x, iy0 + 1, np.pi / 2)
    elif kind == "construction":
        for _ in range(rng.integers(2, 5)):
            b.paint_ellipse(U(ix0, ix1), U(iy0, iy1), rng.uniform(4, 12), rng.uniform(4, 12), S_GRAVEL)
        # fence of barriers along the inner edge
        for x in np.arange(ix0 + 1, ix1 - 1, 2.1):
            for yy in (iy0 + 0.4, iy1 - 0.4):
                if rng.random() < 0.8:
                    cat, size, parts = make_small(b, "barrier")
                    b.obj(cat, (x, yy), 0.0, (size[0], size[1], size[2] + SLAB_HEIGHT), _raised(parts))
        cx, cy = (ix0 + ix1) / 2, (iy0 + iy1) / 2
        for _ in range(rng.integers(1, 4)):
            size, parts = make_vehicle(b, "vehicle.construction")
            b.obj("vehicle.construction", (U(ix0 + 5, ix1 - 5), U(iy0 + 5, iy1 - 5)),
                  rng.uniform(-np.pi, np.pi), (size[0], size[1], size[2] + SLAB_HEIGHT), _raised(parts))
        for _ in range(rng.integers(2, 6)):
            cat, size, parts = make_small(b, "debris" if rng.random() < 0.5 else "cone")
            b.obj(cat, (U(ix0 + 2, ix1 - 2), U(iy0 + 2, iy1 - 2)), rng.uniform(-np.pi, np.pi),
                  (size[0], size[1], size[2] + SLAB_HEIGHT), _raised(parts))
        if rng.random() < 0.6:
            size, parts = make_vehicle(b, "vehicle.trailer")
            b.obj("vehicle.trailer", (cx, iy1 - 6), 0.0, (size[0], size[1], size[2] + SLAB_HEIGHT), _raised(parts))
        b.static(BOX, (cx, cy, SLAB_HEIGHT + 1.5), (3, 2, 1.5), 0, C["manmade"], M_WALL, b.jitter([0.8, 0.8, 0.75]), 0.0)


def _points_of_interest(b: _Builder, road: Road, yroads, x_start, travel):
    """Rare classes placed in the parking strips / sidewalks next to the first part of the ego route."""
    rng = b.rng
    hw = road.half_width
    blocked = [(r.pos - r.half_width - 5.5, r.pos + r.half_width + 5.5) for r in yroads]
    lengths = {"truck_trailer": 24.0, "bus_stop": 14.0, "road_works": 12.0, "motorcycles": 10.0, "bicycles": 6.0,
               "bins": 5.0}
    # free stretches of each side of the ego road near the start, away from intersections
    lo_w, hi_w = x_start - 38.0, x_start + 46.0
    free = {}
    for side_ in (1, -1):
        spans = [(lo_w, hi_w)]
        for a, c in blocked:
            spans = [piece for s0, s1 in spans for piece in ((s0, min(s1, a)), (max(s0, c), s1)) if piece[1] - piece[0] > 1]
        free[side_] = spans
    placements = []
    for kind in lengths:  # longest first
        need = lengths[kind]
        sides = [1, -1] if rng.random() < 0.5 else [-1, 1]
        done = False
        for side_ in sides:
            for n, (s0, s1) in enumerate(free[side_]):
                if s1 - s0 >= need:
                    start = s0 + rng.uniform(0, min(4.0, s1 - s0 - need))
                    placements.append((kind, start + need / 2, side_))
                    free[side_][n] = (start + need, s1)
                    done = True
                    break
            if done:
                break
    for kind, s, side in placements:
        qpark = side * (hw - road.park_w / 2)
        qwalk = side * (hw + 1.6)
        yaw_fwd = 0.0 if side < 0 else np.pi
        if kind == "bus_stop":
            size, parts = make_vehicle(b, "vehicle.bus.rigid")
            b.obj("vehicle.bus.rigid", road.point(s, qpark), yaw_fwd, size, parts)
            p = road.point(s, side * (hw + 2.6))
            b.static(BOX, (p[0], p[1], SLAB_HEIGHT + 2.5), (2.0, 0.8, 0.05), 0, C["manmade"], M_METAL, (0.5, 0.5, 0.55))
            q = road.point(s, side * (hw + 3.3))
            b.static(BOX, (q[0], q[1], SLAB_HEIGHT + 1.25), (2.0, 0.04, 1.25), 0, C["manmade"], M_WALL, (0.6, 0.7, 0.75))
            for k in range(rng.integers(1, 4)):
                size, parts = make_pedestrian(b)
                b.obj("human.pedestrian.adult", road.point(s + rng.uniform(-2, 2), side * (hw + rng.uniform(1, 2.2))),
                      rng.uniform(-np.pi, np.pi), (size[0], size[1], size[2] + SLAB_HEIGHT), _raised(parts))
        elif kind == "road_works":
            for k in range(4):
                cat, size, parts = make_small(b, "cone")
                b.obj(cat, road.point(s - 5 + k * 2.5, side * (hw - road.park_w + 0.5)), 0.0, size, parts)
            for k in range(2):
                cat, size, parts = make_small(b, "barrier")
                b.obj(cat, road.point(s - 3 + k * 2.2, side * (hw - 0.5)), 0.0, size, parts)
            size, parts = make_vehicle(b, "vehicle.construction")
            p = road.point(s + 1, side * (hw + 4.0 + size[0] / 2))
            b.obj("vehicle.construction", p, yaw_fwd, (size[0], size[1], size[2] + SLAB_HEIGHT), _raised(parts))
        elif kind == "truck_trailer":
            size, parts = make_vehicle(b, "vehicle.truck")
            b.obj("vehicle.truck", road.point(s - 0.5 - size[1] / 2, qpark), 0.0, size, parts)
            size, parts = make_vehicle(b, "vehicle.trailer")
            b.obj("vehicle.trailer", road.point(s + 0.5 + size[1] / 2, qpark), 0.0, size, parts)
        elif kind == "motorcycles":
            for k in range(rng.integers(2, 4)):
                size, parts = make_vehicle(b, "vehicle.motorcycle")
                b.obj("vehicle.motorcycle", road.point(s - 3 + 1.2 * k, qpark), np.pi / 2 + 0.3, size, parts)
            size, parts = make_vehicle(b, "vehicle.car")
            b.obj("vehicle.car", road.point(s + 4, qpark), 0.0, size, parts)
        elif kind == "bicycles":
            for k in range(rng.integers(3, 6)):
                size, parts = make_vehicle(b, "vehicle.bicycle")
                b.obj("vehicle.bicycle", road.point(s - 2 + 0.9 * k, qwalk), np.pi / 2,
                      (size[0], size[1], size[2] + SLAB_HEIGHT), _raised(parts))
            p = road.point(s, qwalk)
            b.obj("static_object.bicycle_rack", (p[0], p[1]), 0.0, (0.3, 5.0, 0.8 + SLAB_HEIGHT),
                  _raised([(BOX, (0, 0, 0.4), (2.5, 0.05, 0.4), 0.0, C["others"], M_METAL, (0.5, 0.5, 0.52), 0.0)]))
        elif kind == "bins":
            for k in range(rng.integers(2, 4)):
                cat, size, parts = make_small(b, "bin")
                b.obj(cat, road.point(s + 0.8 * k, qwalk), 0.0, (size[0], size[1], size[2] + SLAB_HEIGHT), _raised(parts))
            size, parts = make_pedestrian(b)
            b.obj("human.pedestrian.adult", road.point(s + 3, qwalk), 0.0, (size[0], size[1], size[2] + SLAB_HEIGHT),
                  _raised(parts))


def _finish(b: _Builder, config, scene_index, route_xy, route_s, speed, ego_s0, roads) -> World:
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
