"""Occ3D ground-truth files: `gts/<scene>/<sample_token>/labels.npz`.

Keys `semantics`, `mask_lidar`, `mask_camera`, each (X, Y, Z) uint8 in axis order [x, y, z];
semantics 0..16 are classes, 17 = free, 255 = unknown (pseudo-labels only).
The masks are stored as uint8 0/1 and must be used as bool.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ago_runtime.atomic import save_npz
from ago_runtime.readers import open_npz, read_npz
from ago_runtime.errors import AgoInputError

KEYS = ("semantics", "mask_lidar", "mask_camera")


def read_voxel_arrays(path: str | Path, keys, what: str, shape: tuple[int, int, int] | None = None
                      ) -> dict[str, np.ndarray]:
    """The arrays `keys` of a ground-truth npz (bounded reading), checked to share one 3-D shape, and that
    shape to be `shape` when given (Occ3D-nuScenes labels.npz, Occ3D-Waymo files)."""
    path = Path(path)
    arrays = read_npz(path, keys, what=what)
    shapes = {k: a.shape for k, a in arrays.items()}
    first = arrays[keys[0]]
    if len(set(shapes.values())) != 1 or first.ndim != 3:
        raise AgoInputError(path, f"arrays must share one 3-D shape, got {shapes}")
    if shape is not None and tuple(first.shape) != tuple(shape):
        raise AgoInputError(path, f"shape {first.shape} does not match the grid {tuple(shape)}")
    return arrays


@dataclass
class Occ3DLabels:
    semantics: np.ndarray    # (X, Y, Z) uint8
    mask_lidar: np.ndarray   # (X, Y, Z) uint8 0/1
    mask_camera: np.ndarray  # (X, Y, Z) uint8 0/1

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.semantics.shape)

    @classmethod
    def load(cls, path: str | Path, shape: tuple[int, int, int] | None = None) -> "Occ3DLabels":
        """Read and check a labels.npz. `shape`, when given, must match (e.g. Grid.shape)."""
        arrays = read_voxel_arrays(path, KEYS, "Occ3D labels file", shape)
        return cls(*(arrays[k].astype(np.uint8) for k in KEYS))

    def save(self, path: str | Path) -> None:
        save_npz(path, semantics=self.semantics.astype(np.uint8), mask_lidar=self.mask_lidar.astype(np.uint8),
                 mask_camera=self.mask_camera.astype(np.uint8))


def labels_path(gts_root: str | Path, scene: str, sample_token: str) -> Path:
    return Path(gts_root) / scene / sample_token / "labels.npz"


def load_semantics(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read `semantics` (X, Y, Z) uint8 and, when present, `mask_camera` (as bool) from an npz.

    Raises AgoInputError naming the file for anything unreadable or malformed.
    """
    path = Path(path)
    with open_npz(path, "labels file") as z:
        if "semantics" not in z.files:
            raise AgoInputError(path, f"no 'semantics' array (found {sorted(z.files)})")
        sem = np.asarray(z["semantics"])
        mask = np.asarray(z["mask_camera"]) if "mask_camera" in z.files else None
    if sem.ndim != 3:
        raise AgoInputError(path, f"'semantics' must be a 3-D (X, Y, Z) array, got shape {sem.shape}")
    if sem.size == 0:
        raise AgoInputError(path, f"'semantics' is an empty grid {sem.shape}")
    if not np.issubdtype(sem.dtype, np.integer):
        raise AgoInputError(path, f"'semantics' must hold integer labels, got dtype {sem.dtype}")
    if sem.size and (sem.min() < 0 or sem.max() > 255):
        raise AgoInputError(path, f"'semantics' labels must lie in 0..255, found {sem.min()}..{sem.max()}")
    if mask is not None and mask.shape != sem.shape:
        raise AgoInputError(path, f"'mask_camera' shape {mask.shape} != 'semantics' shape {sem.shape}")
    return sem.astype(np.uint8), (None if mask is None else mask.astype(bool))
