"""Street furniture along the sidewalks: street lights, signs and traffic lights (class manmade)."""

from __future__ import annotations

import numpy as np

from ago_runtime.classes import OCC3D_ID as C

from .builder import M_METAL, M_SIGN, M_TLIGHT, SLAB_HEIGHT, Builder
from .raycast import BOX, CYL


def add_street_light(b: Builder, x, y, facing_yaw):
    h = b.rng.uniform(6.5, 9.0)
    grey = b.jitter([0.45, 0.47, 0.5])
    b.static(CYL, (x, y, SLAB_HEIGHT + h / 2), (0.1, 0.1, h / 2), 0, C["manmade"], M_METAL, grey)
    dx, dy = np.cos(facing_yaw), np.sin(facing_yaw)
    b.static(BOX, (x + dx * 0.9, y + dy * 0.9, SLAB_HEIGHT + h - 0.1), (0.9, 0.07, 0.07), facing_yaw, C["manmade"], M_METAL, grey)
    b.static(BOX, (x + dx * 1.7, y + dy * 1.7, SLAB_HEIGHT + h - 0.2), (0.35, 0.15, 0.08), facing_yaw, C["manmade"], M_METAL,
             (0.8, 0.8, 0.75))


def add_sign(b: Builder, x, y, facing_yaw):
    h = b.rng.uniform(2.2, 2.8)
    b.static(CYL, (x, y, SLAB_HEIGHT + h / 2), (0.04, 0.04, h / 2), 0, C["manmade"], M_METAL, (0.55, 0.55, 0.57))
    color = [[0.8, 0.1, 0.1], [0.1, 0.3, 0.75], [0.95, 0.95, 0.95], [0.95, 0.8, 0.1]][b.rng.integers(4)]
    b.static(BOX, (x, y, SLAB_HEIGHT + h + 0.3), (0.03, 0.35, 0.35), facing_yaw, C["manmade"], M_SIGN, color,
             b.rng.integers(3))


def add_traffic_light(b: Builder, x, y, facing_yaw):
    h = b.rng.uniform(3.6, 4.4)
    b.static(CYL, (x, y, SLAB_HEIGHT + h / 2), (0.09, 0.09, h / 2), 0, C["manmade"], M_METAL, (0.3, 0.3, 0.32))
    b.static(BOX, (x, y, SLAB_HEIGHT + h + 0.5), (0.18, 0.2, 0.5), facing_yaw, C["manmade"], M_TLIGHT, (0.12, 0.12, 0.12),
             b.rng.integers(3))
