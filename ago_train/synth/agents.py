"""The movable objects of a synthetic scene and where they go: vehicles, riders, pedestrians, small objects.

Templates (parts in the object frame: x forward, y left, z from the ground): `make_vehicle` (car, truck,
bus, trailer, construction vehicle, motorcycle, bicycle), `add_rider`, `make_pedestrian`, `make_small`
(cone, barrier, bin, stroller, debris). Placement: `add_traffic` (parked and moving vehicles),
`add_crossing_pedestrians` (zebra crossings), `sidewalk_walkers` (around a block) and
`add_points_of_interest` (rare classes next to the start of the ego route, so every class appears near
the ego in every scene).
"""

from __future__ import annotations

import numpy as np

from ago_runtime.classes import OCC3D_ID as C

from .builder import (M_BARRIER, M_BODY, M_BUS, M_CABIN, M_CONCRETE, M_CONE, M_METAL, M_PERSON, M_PLASTIC, M_SKIN,
                      M_TIRE, M_WALL, SLAB_HEIGHT, Builder, raised)
from .raycast import BOX, CONE, CYL, ELL
from .roads import Road

CAR_COLORS = np.array([[0.9, 0.9, 0.9], [0.1, 0.1, 0.12], [0.55, 0.56, 0.6], [0.7, 0.1, 0.1], [0.1, 0.2, 0.55],
                       [0.75, 0.75, 0.78], [0.25, 0.35, 0.3], [0.85, 0.75, 0.2], [0.4, 0.25, 0.15], [0.3, 0.3, 0.32]])
CLOTH_COLORS = np.array([[0.1, 0.1, 0.12], [0.2, 0.25, 0.45], [0.6, 0.1, 0.1], [0.85, 0.85, 0.8], [0.3, 0.4, 0.25],
                         [0.5, 0.45, 0.35], [0.9, 0.6, 0.1], [0.4, 0.4, 0.42]])


def _wheels(l, w, r=0.33, width=0.22):
    rows = []
    for sx in (0.34, -0.34):
        for sy in (1, -1):
            rows.append((BOX, (sx * l, sy * (w / 2 - width / 2 + 0.02), r), (r, width / 2, r), 0.0, None, M_TIRE,
                         (0.06, 0.06, 0.06), 0.0))
    return rows


def make_vehicle(b: Builder, category: str):
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


def add_rider(b: Builder, parts, size, cls):
    """A person sitting on a bicycle/motorcycle (labelled as the vehicle, as in nuScenes lidarseg boxes)."""
    cloth = b.jitter(CLOTH_COLORS[b.rng.integers(len(CLOTH_COLORS))])
    parts.append((CYL, (-0.1, 0, 1.25), (0.2, 0.2, 0.35), 0.0, cls, M_PERSON, cloth, 0.0))
    parts.append((ELL, (-0.05, 0, 1.72), (0.11, 0.1, 0.13), 0.0, cls, M_SKIN, b.jitter([0.75, 0.58, 0.45], 0.25), 0.0))
    return (size[0], size[1], 1.85)


def make_pedestrian(b: Builder):
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


def make_small(b: Builder, what: str):
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


def add_traffic(b: Builder, roads: list[Road], xroads: list[Road], yroads: list[Road], ego_road: Road, half: float,
                x_start: float) -> None:
    """Parked vehicles in the parking strips (none where the ego starts) and vehicles driving along every
    lane (riders on motorcycles and bicycles; bicycles keep to the outer lane), at constant velocity."""
    config, rng = b.cfg, b.rng
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


def add_crossing_pedestrians(b: Builder, yroads: list[Road], ego_road: Road, x_start: float, travel: float) -> None:
    """Pedestrians walking over the zebra crossings of the ego road near the route."""
    rng = b.rng
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


def sidewalk_walkers(b: Builder, x0, x1, y0, y1, sw, verge=0.0):
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
        parts = raised(parts)
        b.obj("human.pedestrian.adult", xy, yaw, (size[0], size[1], size[2] + SLAB_HEIGHT), parts, velocity=vel)
        if rng.random() < 0.06:  # a stroller or a cart pushed in front
            cat, ssize, sparts = make_small(b, "stroller")
            sparts = raised(sparts)
            d = np.array([np.cos(yaw), np.sin(yaw)])
            b.obj(cat, tuple(np.asarray(xy) + 0.9 * d), yaw, (ssize[0], ssize[1], ssize[2] + SLAB_HEIGHT), sparts,
                  velocity=vel)


def add_points_of_interest(b: Builder, road: Road, yroads, x_start, travel):
    """Rare classes placed in the parking strips / sidewalks next to the first part of the ego route."""
    rng = b.rng
    hw = road.half_width
    blocked = [(r.pos - r.half_width - 5.5, r.pos + r.half_width + 5.5) for r in yroads]
    lengths = {"truck_trailer": 24.0, "barrier_row": 14.0, "bus_stop": 14.0, "road_works": 12.0, "motorcycles": 10.0,
               "bicycles": 6.0, "bins": 5.0}
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
                      rng.uniform(-np.pi, np.pi), (size[0], size[1], size[2] + SLAB_HEIGHT), raised(parts))
        elif kind == "road_works":
            for k in range(4):
                cat, size, parts = make_small(b, "cone")
                b.obj(cat, road.point(s - 5 + k * 2.5, side * (hw - road.park_w + 0.5)), 0.0, size, parts)
            for k in range(int(rng.integers(2, 5))):
                cat, size, parts = make_small(b, "barrier")
                b.obj(cat, road.point(s - 3 + k * 2.2, side * (hw - 0.5)), 0.0, size, parts)
            size, parts = make_vehicle(b, "vehicle.construction")
            p = road.point(s + 1, side * (hw + 4.0 + size[0] / 2))
            b.obj("vehicle.construction", p, yaw_fwd, (size[0], size[1], size[2] + SLAB_HEIGHT), raised(parts))
        elif kind == "barrier_row":  # a closed-off road edge: a line of 4-6 barriers (as nuScenes' lane-side barriers)
            n = int(rng.integers(4, 7))
            for k in range(n):
                cat, size, parts = make_small(b, "barrier")
                b.obj(cat, road.point(s + (k - (n - 1) / 2) * 2.2, side * (hw - 0.5)), 0.0, size, parts)
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
                      (size[0], size[1], size[2] + SLAB_HEIGHT), raised(parts))
            p = road.point(s, qwalk)
            b.obj("static_object.bicycle_rack", (p[0], p[1]), 0.0, (0.3, 5.0, 0.8 + SLAB_HEIGHT),
                  raised([(BOX, (0, 0, 0.4), (2.5, 0.05, 0.4), 0.0, C["others"], M_METAL, (0.5, 0.5, 0.52), 0.0)]))
        elif kind == "bins":
            for k in range(rng.integers(2, 4)):
                cat, size, parts = make_small(b, "bin")
                b.obj(cat, road.point(s + 0.8 * k, qwalk), 0.0, (size[0], size[1], size[2] + SLAB_HEIGHT), raised(parts))
            size, parts = make_pedestrian(b)
            b.obj("human.pedestrian.adult", road.point(s + 3, qwalk), 0.0, (size[0], size[1], size[2] + SLAB_HEIGHT),
                  raised(parts))
