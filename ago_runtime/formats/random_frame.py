"""A random images folder, for tests and benchmarks: six smooth random JPEGs named by camera and a
calib.json of a nuScenes-like rig (`ago infer --images DIR` reads it like a real frame; docs/runtime.md)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ago_runtime.formats.calibration import save_calibration
from ago_runtime.geometry.camera import CAMERA_NAMES, Rig

__all__ = ["write_random_frame"]


def write_random_frame(folder: str | Path, width: int = 400, height: int = 225, seed: int = 0,
                       calib: bool = True) -> Path:
    """Six smooth random (height, width) JPEGs in `folder` (made if missing) and, with calib, its calib.json
    (Rig.nuscenes_like at that size). Same seed, same bytes. Gives the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for name in CAMERA_NAMES:
        coarse = rng.uniform(0, 255, (height // 8 + 1, width // 8 + 1, 3)).astype(np.float32)
        image = np.clip(cv2.resize(coarse, (width, height)), 0, 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"{name}.jpg"), image)
    if calib:
        save_calibration(folder / "calib.json", Rig.nuscenes_like(width, height))
    return folder
