"""Trees (broadleaf or conifer) and bushes, as static primitives of class vegetation."""

from __future__ import annotations

import numpy as np

from ago_runtime.classes import OCC3D_ID as C

from .builder import M_BARK, M_FOLIAGE, SLAB_HEIGHT, Builder
from .raycast import CONE, CYL, ELL


def add_tree(b: Builder, x, y, z0=SLAB_HEIGHT, scale=1.0):
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


def add_bush(b: Builder, x, y, z0=SLAB_HEIGHT):
    r = b.rng.uniform(0.5, 1.3)
    b.static(ELL, (x, y, z0 + r * 0.55), (r * b.rng.uniform(1.0, 1.8), r, r * 0.75), b.rng.uniform(0, np.pi),
             C["vegetation"], M_FOLIAGE, b.jitter([0.22, 0.4, 0.16], 0.15), b.rng.uniform(0, 100))
