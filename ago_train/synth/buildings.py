"""Buildings: a box per building (facade window spacing in `param`), sometimes a rooftop structure."""

from __future__ import annotations

import numpy as np

from ago_runtime.classes import OCC3D_ID as C

from .builder import M_BUILDING, M_WALL, SLAB_HEIGHT, Builder
from .raycast import BOX

BUILDING_COLORS = np.array([[0.55, 0.28, 0.22], [0.80, 0.72, 0.58], [0.62, 0.62, 0.64], [0.86, 0.85, 0.80],
                            [0.38, 0.38, 0.42], [0.45, 0.55, 0.62], [0.70, 0.55, 0.40], [0.75, 0.78, 0.72]])


def add_building(b: Builder, cx, cy, yaw, width, depth, height):
    """width along the facade (local y), depth away from the street (local x)."""
    color = b.jitter(BUILDING_COLORS[b.rng.integers(len(BUILDING_COLORS))], 0.1)
    spacing = b.rng.uniform(2.2, 3.8) if b.rng.random() < 0.85 else 0.0
    b.static(BOX, (cx, cy, SLAB_HEIGHT + height / 2), (depth / 2, width / 2, height / 2), yaw, C["manmade"], M_BUILDING,
             color, spacing)
    if b.rng.random() < 0.3:  # rooftop structure
        b.static(BOX, (cx, cy, SLAB_HEIGHT + height + 1.0), (depth / 5, width / 5, 1.0), yaw, C["manmade"], M_WALL,
                 color * 0.9)
