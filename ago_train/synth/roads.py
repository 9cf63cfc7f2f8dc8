"""The road network of a synthetic scene, its markings, and the ego's route along it.

`road_network` lays out the Manhattan grid (1 or 2 lanes per direction, optional parking strips, a
painted line, raised traffic island or tram rail strip on the centre line); `paint_roads` paints it on
the surface raster (roads, strips, lane markings, zebra crossings); `ego_route` is the ego's path on the
inner lane of the road y = 0, with maybe one turn.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .builder import M_GROUND, S_ISLAND, S_PARKING, S_RAIL, S_ROAD, SLAB_HEIGHT, Builder
from .config import SynthConfig
from .raycast import BOX, MAP_CLASS


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


def road_network(rng, config: SynthConfig, half: float, x_start: float) -> tuple[list[Road], list[Road], Road]:
    """The Manhattan grid: roads along x (at y positions, one at y = 0 for the ego), roads along y, and the
    ego road. Gives (xroads, yroads, ego_road)."""
    ys = _positions(rng, 0.0, config.block_min, config.block_max, half)
    # the ego starts in a long block (room for the points of interest), the next crossing ~40 m ahead
    first = x_start + rng.uniform(36, 48)
    gap = rng.uniform(78, 95)
    xs = sorted([p for p in _positions(rng, first, config.block_min, config.block_max, half) if p >= first]
                + [p for p in _positions(rng, first - gap, config.block_min, config.block_max, half) if p <= first - gap])
    xroads = [_make_road(rng, 0, y, ego=(y == 0.0)) for y in ys]
    yroads = [_make_road(rng, 1, x) for x in xs]
    ego_road = xroads[ys.index(0.0)]
    return xroads, yroads, ego_road


def ego_route(rng, ego_road: Road, yroads: list[Road], x_start: float, travel: float) -> tuple[np.ndarray, np.ndarray]:
    """The ego path (K, 2) in 0.1 m steps and its arclength (K,): the inner forward lane of the road
    y = 0, maybe one turn at an intersection ahead."""
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
    return route_xy, route_s


def paint_roads(b: Builder, roads: list[Road], xroads: list[Road], yroads: list[Road], half: float) -> None:
    """The roads on the surface raster: asphalt, parking strips, centre islands / tram rails (islands also
    as raised slabs), lane lines, dashed lines and zebra crossings between the intersections."""
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
