"""`Grid`: an axis-aligned voxel grid in the ego frame (metres), axis order [x, y, z].

Occ3D-nuScenes: range [-40, -40, -1, 40, 40, 5.4] m, 0.4 m voxels -> (200, 200, 16);
voxel (i, j, k) has its centre at range_min + voxel_size * (index + 0.5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MAX_GRID_VOXELS = 1 << 25      # a model's or bundle's grid of more voxels than this is refused (Occ3D: 640 k)


@dataclass(frozen=True)
class Grid:
    range_min: tuple[float, float, float] = (-40.0, -40.0, -1.0)
    range_max: tuple[float, float, float] = (40.0, 40.0, 5.4)
    voxel_size: tuple[float, float, float] = (0.4, 0.4, 0.4)

    @classmethod
    def occ3d(cls) -> "Grid":
        """Occ3D-nuScenes' grid: 200 x 200 x 16 voxels of 0.4 m."""
        return cls()

    @classmethod
    def with_shape(cls, shape: tuple[int, int, int],
                   range_min=(-40.0, -40.0, -1.0), range_max=(40.0, 40.0, 5.4)) -> "Grid":
        """The Occ3D range cut into `shape` voxels (e.g. (100, 100, 8) = 0.8 m voxels)."""
        size = tuple(float((b - a) / n) for a, b, n in zip(range_min, range_max, shape))
        return cls(tuple(map(float, range_min)), tuple(map(float, range_max)), size)

    @classmethod
    def parse(cls, text: str, option: str = "--grid") -> "Grid":
        """'100x100x8' -> Grid.with_shape((100, 100, 8)); anything else is one AgoInputError naming `option`."""
        from ago_runtime.errors import AgoInputError

        try:
            shape = tuple(int(p) for p in str(text).lower().split("x"))
        except ValueError:
            shape = ()
        if len(shape) != 3 or min(shape) <= 0 or max(shape) > 4096:
            raise AgoInputError(option, f"expected XxYxZ voxel counts like 100x100x8, got {text!r}")
        return cls.with_shape(shape)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(
            int(round((b - a) / s)) for a, b, s in zip(self.range_min, self.range_max, self.voxel_size)
        )

    @property
    def num_voxels(self) -> int:
        x, y, z = self.shape
        return x * y * z

    def axis_centres(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-axis voxel centre coordinates (float64), lengths = shape."""
        return tuple(
            a + s * (np.arange(n) + 0.5) for a, s, n in zip(self.range_min, self.voxel_size, self.shape)
        )

    def centres(self) -> np.ndarray:
        """(X, Y, Z, 3) float32 voxel centres in the ego frame."""
        xs, ys, zs = self.axis_centres()
        return np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).astype(np.float32)

    def points_to_index(self, points_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ego-frame points (N, >=3) -> (N, 3) int64 voxel indices and an (N,) bool 'inside' mask.

        Indices of points outside the grid are clipped into range; use the mask.
        """
        p = np.asarray(points_ego, dtype=np.float64)[:, :3]
        idx = np.floor((p - np.asarray(self.range_min)) / np.asarray(self.voxel_size)).astype(np.int64)
        shape = np.asarray(self.shape)
        inside = np.all((idx >= 0) & (idx < shape), axis=1)
        return np.clip(idx, 0, shape - 1), inside

    def flat_index(self, idx: np.ndarray) -> np.ndarray:
        """(N, 3) voxel indices -> (N,) indices into the flattened (X*Y*Z) grid (C order)."""
        X, Y, Z = self.shape
        return (idx[:, 0] * Y + idx[:, 1]) * Z + idx[:, 2]

    def to_dict(self) -> dict:
        return {"range_min": list(self.range_min), "range_max": list(self.range_max),
                "voxel_size": list(self.voxel_size), "shape": list(self.shape)}

    @classmethod
    def from_dict(cls, d: dict) -> "Grid":
        return cls(tuple(map(float, d["range_min"])), tuple(map(float, d["range_max"])),
                   tuple(map(float, d["voxel_size"])))


def check_grid_dict(grid, source, key: str = "model.grid") -> None:
    """A grid section (Grid.to_dict: range_min, range_max, voxel_size, [shape]) that makes a grid of
    1 .. MAX_GRID_VOXELS voxels, with a stated shape that agrees; else AgoInputError(source, "<key>: problem").
    The one rule for a training config's model.grid and bundle.json's grid / model_grid."""
    from ago_runtime.errors import AgoInputError

    need = ("range_min", "range_max", "voxel_size")
    if not isinstance(grid, dict) or any(k not in grid for k in need):
        raise AgoInputError(source, f"{key} needs {', '.join(need)} (3 numbers each), got {str(grid)[:120]}")
    try:
        values = [[float(v) for v in grid[k]] for k in need]
        if any(len(v) != 3 or not all(math.isfinite(x) for x in v) for v in values):
            raise ValueError
    except (TypeError, ValueError):
        raise AgoInputError(source, f"{key}: {', '.join(need)} must be 3 finite numbers each") from None
    lo, hi, size = values
    if min(size) <= 0 or any(b <= a for a, b in zip(lo, hi)):
        raise AgoInputError(source, f"{key}: voxel sizes must be > 0 and range_max above range_min")
    if any((b - a) / s > MAX_GRID_VOXELS for a, b, s in zip(lo, hi, size)):
        raise AgoInputError(source, f"{key}: more than {MAX_GRID_VOXELS} voxels along an axis")
    shape = Grid(tuple(lo), tuple(hi), tuple(size)).shape
    if min(shape) < 1 or math.prod(shape) > MAX_GRID_VOXELS:
        raise AgoInputError(source, f"{key}: {list(shape)} voxels (1 to {MAX_GRID_VOXELS} in all)")
    stated = grid.get("shape")
    if stated is not None and (not isinstance(stated, (list, tuple)) or list(stated) != list(shape)):
        raise AgoInputError(source, f"{key}: shape {str(stated)[:60]} does not match range and voxel size ({list(shape)})")
