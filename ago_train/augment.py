"""Training augmentation of a whole frame by a symmetry of the ego grid (bird's-eye-view augmentation).

The Occ3D grid is symmetric under y -> -y (a mirror) and under a half turn about z (x, y -> -x, -y).
A frame seen in a mirrored or turned ego frame is another plausible frame; both keep every label,
every voxel and the frozen image features usable:

- half turn (`rot180`): the images are unchanged (the cameras are the same cameras, the rig is just
  described in a turned ego frame): ego2img' = ego2img @ A^-1, labels and E_3D indices turned;
- mirror (`flip_y`): the world is mirrored, so each image is flipped left-right (its features are the
  backbone's features of the flipped image, cached apart), ego2img' = F_img @ ego2img @ A^-1 with
  F_img: u -> W - u (pixel u spans [u, u+1), the convention of the TPV projection), labels and
  E_3D indices mirrored.
A = diag(1, -1, 1) (mirror), diag(-1, -1, 1) (half turn) or diag(-1, 1, 1) (both), in homogeneous 4x4.

`AUGMENTATIONS`: "none", "flip" (mirror with probability 1/2), "flip+rot180" (each of the four with
probability 1/4). `draw(kind, seed, epoch, index)` -> GridTransform, seeded so that a resumed run draws
the same transforms. The exported model and the runtime never see any of this.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

AUGMENTATIONS = ("none", "flip", "flip+rot180")


@dataclass(frozen=True)
class GridTransform:
    flip_y: bool = False     # mirror y -> -y (images flipped left-right)
    rot180: bool = False     # half turn about z (x, y -> -x, -y)

    @property
    def identity(self) -> bool:
        return not (self.flip_y or self.rot180)

    def ego_matrix(self) -> np.ndarray:
        """(4, 4) old ego -> new ego."""
        sx = -1.0 if self.rot180 else 1.0
        sy = (-1.0 if self.rot180 else 1.0) * (-1.0 if self.flip_y else 1.0)
        return np.diag([sx, sy, 1.0, 1.0])

    def ego2img(self, ego2img: np.ndarray, image_width: int) -> np.ndarray:
        """(V, 4, 4) projections (rows u*d, v*d, d, 1 for images `image_width` wide) in the new ego frame."""
        out = np.asarray(ego2img, dtype=np.float64) @ np.linalg.inv(self.ego_matrix())
        if self.flip_y:
            f = np.eye(4)
            f[0, 0], f[0, 2] = -1.0, float(image_width)
            out = f @ out
        return out.astype(np.float32)

    def volume(self, vol: np.ndarray) -> np.ndarray:
        """(X, Y, Z[, ...]) grid array -> the same array in the new ego frame."""
        if self.rot180:
            vol = vol[::-1, ::-1]
        if self.flip_y:
            vol = vol[:, ::-1]
        return np.ascontiguousarray(vol)

    def flat_index(self, index: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
        """Flat C-order voxel indices -> the indices of the same voxels in the new ego frame."""
        X, Y, Z = shape
        x, y, z = index // (Y * Z), (index // Z) % Y, index % Z
        if self.rot180:
            x, y = X - 1 - x, Y - 1 - y
        if self.flip_y:
            y = Y - 1 - y
        return (x * Y + y) * Z + z


def draw(kind: str, seed: int, epoch: int, index: int) -> GridTransform:
    if kind not in AUGMENTATIONS:
        raise ValueError(f"unknown augmentation {kind!r}; expected one of {AUGMENTATIONS}")
    if kind == "none":
        return GridTransform()
    r = np.random.default_rng([int(seed), int(epoch), int(index), 7]).integers(0, 4)
    if kind == "flip":
        return GridTransform(flip_y=bool(r % 2))
    return GridTransform(flip_y=bool(r % 2), rot180=bool(r // 2))
