"""TPV planes -> per-voxel features.

Takes the three plane maps plane_xy (B, D, Xt, Yt), plane_xz (B, D, Xt, Zt), plane_yz (B, D, Yt, Zt)
and the grid shape (X, Y, Z). Planes coarser than the grid are upsampled bilinearly
(align_corners=False) to (X, Y), (X, Z), (Y, Z). A voxel's feature is the sum of the three plane
features it projects onto: f[x, y, z] = xy[x, y] + xz[x, z] + yz[y, z].
Gives (B, N, D) with N = X*Y*Z in C order over [x, y, z] (= ago_runtime.geometry.grid.Grid.flat_index).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def upsample_planes(planes: dict[str, torch.Tensor], grid_shape: tuple[int, int, int]) -> dict[str, torch.Tensor]:
    X, Y, Z = grid_shape
    size = {"xy": (X, Y), "xz": (X, Z), "yz": (Y, Z)}
    out = {}
    for p, m in planes.items():
        if tuple(m.shape[-2:]) != size[p]:
            m = F.interpolate(m, size=size[p], mode="bilinear", align_corners=False)
        out[p] = m
    return out


def planes_to_voxels(planes: dict[str, torch.Tensor], grid_shape: tuple[int, int, int]) -> torch.Tensor:
    """{"xy", "xz", "yz"} plane maps -> (B, X*Y*Z, D) voxel features."""
    up = upsample_planes(planes, grid_shape)
    xy, xz, yz = up["xy"], up["xz"], up["yz"]
    vox = xy.unsqueeze(-1) + xz.unsqueeze(-2) + yz.unsqueeze(-3)      # (B, D, X, Y, Z)
    B, D = vox.shape[:2]
    return vox.reshape(B, D, -1).transpose(1, 2)


def planes_at_voxels(planes: dict[str, torch.Tensor], grid_shape: tuple[int, int, int],
                     voxel_index: torch.Tensor) -> torch.Tensor:
    """Features of selected voxels only: voxel_index (B, M) or (M,) int64 flat indices (C order over [x, y, z])
    -> (B, M, D), equal to planes_to_voxels(...)[b, voxel_index[b]] but without building the full grid."""
    X, Y, Z = grid_shape
    up = upsample_planes(planes, grid_shape)
    B, D = up["xy"].shape[:2]
    if voxel_index.dim() == 1:
        voxel_index = voxel_index.unsqueeze(0).expand(B, -1)
    x = voxel_index // (Y * Z)
    y = (voxel_index // Z) % Y
    z = voxel_index % Z

    def take(m: torch.Tensor, flat: torch.Tensor) -> torch.Tensor:       # m (B, D, R, C), flat (B, M)
        return torch.gather(m.reshape(B, D, -1), 2, flat.unsqueeze(1).expand(B, D, flat.shape[1]))

    f = take(up["xy"], x * Y + y) + take(up["xz"], x * Z + z) + take(up["yz"], y * Z + z)
    return f.transpose(1, 2)
