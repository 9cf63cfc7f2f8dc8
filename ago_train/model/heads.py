"""Per-voxel heads: the decoder MLP (TPV feature -> hidden h) and the modality adapter (F_3D -> hidden g).

The last linear layers (`decoder_out`: Dh -> C, `adapter_out`: Da -> C) live on `AGOModel` as plain
nn.Linear with bias, so the ONNX runtime can fold a text bank T (P, C) into them:
S = h (W^T T^T) + b T^T.

Decoder: D -> Dh with softplus, then (decoder_layers - 1) more Dh -> Dh softplus layers.
Adapter (depth d, paper d = 2): d = 1: g = F_3D (adapter_out is the only linear);
d >= 2: g = softplus(W_{d-1} ... softplus(W_1 F_3D + b_1) ...), widths C -> A -> ... -> A.
"""

from __future__ import annotations

import torch
from torch import nn


class DecoderMLP(nn.Module):
    def __init__(self, in_dim: int, hidden: int, layers: int = 1):
        super().__init__()
        mods: list[nn.Module] = []
        dims = [in_dim] + [hidden] * layers
        for a, b in zip(dims[:-1], dims[1:]):
            mods += [nn.Linear(a, b), nn.Softplus()]
        self.net = nn.Sequential(*mods)
        self.out_dim = hidden

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class AdapterHidden(nn.Module):
    """The modality adapter without its last linear: F_3D (.., C) -> g (.., Da)."""

    def __init__(self, embed_dim: int, hidden: int, depth: int):
        super().__init__()
        mods: list[nn.Module] = []
        dims = [embed_dim] + [hidden] * (depth - 1)
        for a, b in zip(dims[:-1], dims[1:]):
            mods += [nn.Linear(a, b), nn.Softplus()]
        self.net = nn.Sequential(*mods)  # empty for depth 1 -> identity
        self.out_dim = dims[-1]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)
