"""City blocks: the raised slab, its sidewalk ring and furniture, and what stands inside.

`add_blocks` fills every block between the roads with one of: urban (buildings, walls, hedges,
courtyard trees), park (lawn, soil, a path, a pond, trees, bushes), parking lot (parked cars, lights)
or construction site (gravel, barrier fence, construction vehicles, debris, cones, a site hut).
"""

from __future__ import annotations

import numpy as np

from ago_runtime.classes import OCC3D_ID as C

from .agents import make_small, make_vehicle, sidewalk_walkers
from .buildings import add_building
from .builder import (M_FOLIAGE, M_GROUND, M_PLASTIC, M_WALL, S_GRASS, S_GRAVEL, S_PARKING, S_PLAZA, S_SIDEWALK,
                      S_SOIL, S_WATER, SLAB_HEIGHT, Builder, raised)
from .furniture import add_sign, add_street_light, add_traffic_light
from .raycast import BOX, CYL, MAP_CLASS
from .roads import Road
from .vegetation import add_bush, add_tree


def add_blocks(b: Builder, xroads: list[Road], yroads: list[Road], half: float, x_start: float) -> None:
    """Every city block between the roads, each of a random kind (no parking lot or park right where the
    ego starts)."""
    rng = b.rng
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
            add_block(b, x0, x1, y0, y1, kind)


def add_block(b: Builder, x0, x1, y0, y1, kind):
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
                b.obj(cat, at(t), facing, (size[0], size[1], size[2] + SLAB_HEIGHT), raised(parts))
            elif r < tree_p + 0.16:
                add_bush(b, *at(t))
            elif r < tree_p + 0.19:
                b.static(CYL, (*at(t), SLAB_HEIGHT + 0.35), (0.15, 0.15, 0.35), 0, C["others"], M_PLASTIC, (0.8, 0.1, 0.1))
            t += rng.uniform(5, 11)
    sidewalk_walkers(b, x0, x1, y0, y1, sw, verge)

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
            b.obj(cat, (U(ix0, ix1), cy + 1.6), 0.0, (size[0], size[1], size[2] + SLAB_HEIGHT), raised(parts))
    elif kind == "parking":
        for row_y in np.arange(iy0 + 3, iy1 - 3, 6.5):
            for x in np.arange(ix0 + 2, ix1 - 2, 2.8):
                if rng.random() < 0.6:
                    cat = str(rng.choice(["vehicle.car", "vehicle.truck", "vehicle.trailer"], p=[0.88, 0.07, 0.05]))
                    size, parts = make_vehicle(b, cat)
                    if cat != "vehicle.car":
                        continue
                    b.obj(cat, (x, row_y), np.pi / 2 + (np.pi if rng.random() < 0.5 else 0), (size[0], size[1], size[2] + SLAB_HEIGHT),
                          raised(parts))
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
                    b.obj(cat, (x, yy), 0.0, (size[0], size[1], size[2] + SLAB_HEIGHT), raised(parts))
        cx, cy = (ix0 + ix1) / 2, (iy0 + iy1) / 2
        for _ in range(rng.integers(1, 4)):
            size, parts = make_vehicle(b, "vehicle.construction")
            b.obj("vehicle.construction", (U(ix0 + 5, ix1 - 5), U(iy0 + 5, iy1 - 5)),
                  rng.uniform(-np.pi, np.pi), (size[0], size[1], size[2] + SLAB_HEIGHT), raised(parts))
        for _ in range(rng.integers(2, 6)):
            cat, size, parts = make_small(b, "debris" if rng.random() < 0.5 else "cone")
            b.obj(cat, (U(ix0 + 2, ix1 - 2), U(iy0 + 2, iy1 - 2)), rng.uniform(-np.pi, np.pi),
                  (size[0], size[1], size[2] + SLAB_HEIGHT), raised(parts))
        if rng.random() < 0.6:
            size, parts = make_vehicle(b, "vehicle.trailer")
            b.obj("vehicle.trailer", (cx, iy1 - 6), 0.0, (size[0], size[1], size[2] + SLAB_HEIGHT), raised(parts))
        b.static(BOX, (cx, cy, SLAB_HEIGHT + 1.5), (3, 2, 1.5), 0, C["manmade"], M_WALL, b.jitter([0.8, 0.8, 0.75]), 0.0)
