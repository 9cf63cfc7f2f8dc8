"""What every part of the synthetic city is built with: surface codes, materials, and the Builder.

- surface codes (S_*) of the 2-D ground raster and their Occ3D class (SURFACE_CLASS);
- materials (M_*: the texture kinds render.py draws);
- SLAB_HEIGHT (the 0.15 m raised city blocks) and RASTER_RES (metres per raster cell);
- `Builder`: the scene's random generator, the surface / marking rasters it paints (world frame,
  row = y, col = x) and the rows of static primitives (world frame) and movable objects (parts in
  the object frame) the other modules add; `raised(parts)` lifts object parts onto a block's slab.
numpy only; no module of the city imports anything above this one.
"""

from __future__ import annotations

import numpy as np

from ago_runtime.classes import OCC3D_ID as C

from .config import SynthConfig

# ---- surface codes of the ground raster, and their Occ3D class --------------------------------
S_ROAD, S_PARKING, S_SIDEWALK, S_GRASS, S_SOIL, S_ISLAND, S_WATER, S_RAIL, S_PLAZA, S_GRAVEL = range(10)
SURFACE_CLASS = np.array([C["driveable_surface"], C["driveable_surface"], C["sidewalk"], C["terrain"], C["terrain"],
                          C["other_flat"], C["other_flat"], C["other_flat"], C["sidewalk"], C["terrain"]], np.uint8)
# ---- materials (texture kinds, see render.py) ----------------------------------------------------
(M_GROUND, M_BUILDING, M_WALL, M_BODY, M_CABIN, M_TIRE, M_FOLIAGE, M_BARK, M_PERSON, M_SKIN, M_METAL, M_SIGN,
 M_TLIGHT, M_CONE, M_BARRIER, M_CONCRETE, M_PLASTIC, M_BUS) = range(18)

SLAB_HEIGHT = 0.15
RASTER_RES = 0.25  # metres per surface-raster cell


class Builder:
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


def raised(parts):
    return [(k, (c[0], c[1], c[2] + SLAB_HEIGHT), h, y, cl, m, co, pa) for k, c, h, y, cl, m, co, pa in parts]
