"""Whole-grid volume helpers that scoring and prediction share (a basics module: it imports only numpy).

`upsample_nearest(volume, (2, 2, 1))`: each voxel repeated along each axis, e.g. a 100 x 100 x 16 prediction
brought to Occ3D's 200 x 200 x 16 before it is scored (ago_runtime.scoring.metric) or matched with labels
(ago_runtime.predict.threshold).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

__all__ = ["upsample_nearest"]


def upsample_nearest(volume: np.ndarray, factor_xyz: int | Sequence[int]) -> np.ndarray:
    """Repeat each voxel `factor` times along each axis: (X, Y, Z) -> (X*fx, Y*fy, Z*fz), same dtype."""
    if isinstance(factor_xyz, (int, np.integer)):
        factor_xyz = (int(factor_xyz),) * volume.ndim
    out = np.asarray(volume)
    if len(factor_xyz) != out.ndim:
        raise ValueError(f"need one factor per axis: volume has {out.ndim} axes, got {tuple(factor_xyz)}")
    for axis, f in enumerate(factor_xyz):
        if int(f) < 1:
            raise ValueError(f"upsampling factors must be >= 1, got {tuple(factor_xyz)}")
        if int(f) > 1:
            out = np.repeat(out, int(f), axis=axis)
    return out
