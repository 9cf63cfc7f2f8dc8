"""`AGOModel`: six camera images -> per-voxel embeddings in the text space.

forward_hidden(images (B, V, 3, H, W) (V cameras, the rig's order) float32 normalised by ago_runtime.geometry.preprocess.Preprocess,
               ego2img (B, V, 4, 4) float32 for the canvases)
  -> h (B, N, Dh) decoder hidden, g (B, N, Da) adapter hidden; N = X*Y*Z, C order over [x, y, z].
forward(images, ego2img, voxel_index=None, prefix=None) -> {"feat": F_3D = decoder_out(h) (B, N, C),
                 "feat_adapted": F~_3D = adapter_out(g) (B, N, C),
                 "free_embedding": (C,), and "free_bias": () when the model has one}
  `prefix` (training with ago_train/feature_cache.py): the frozen backbone stages' maps, a list of
  (B*V, C_l, H_l, W_l) tensors = backbone.frozen_prefix(images); `images` is then not used (may be None).

Pipeline: backbone (strides 8/16/32) -> FPN (tpv_dim) -> TPV encoder (three planes) ->
planes_to_voxels -> decoder MLP -> decoder_out -> adapter.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

from .aggregate import planes_at_voxels, planes_to_voxels
from .backbone import build_backbone
from .fpn import FPN
from .heads import AdapterHidden, DecoderMLP
from .tpv import TPVEncoder

if TYPE_CHECKING:   # annotations only: ModelConfig.build() imports this module
    from .config import ModelConfig


class AGOModel(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.grid_shape = cfg.grid_obj().shape
        self.backbone = build_backbone(cfg.backbone, cfg.image_height, cfg.image_width, cfg.pretrained,
                                       cfg.frozen_stages)
        self.fpn = FPN(self.backbone.out_channels, cfg.tpv_dim)
        self.encoder = TPVEncoder(cfg, levels=3)
        self.decoder = DecoderMLP(cfg.tpv_dim, cfg.hidden_dim, cfg.decoder_layers)
        self.decoder_out = nn.Linear(cfg.hidden_dim, cfg.embed_dim)
        self.adapter = AdapterHidden(cfg.embed_dim, cfg.adapter_hidden, cfg.adapter_depth)
        self.adapter_out = nn.Linear(self.adapter.out_dim, cfg.embed_dim)
        free = torch.randn(cfg.embed_dim)
        self.free_embedding = nn.Parameter(free / free.norm())
        # the free score's bias (ModelConfig.free_bias); None = the paper's plain dot product
        self.free_bias = nn.Parameter(torch.zeros(())) if cfg.free_bias else None

    @property
    def num_voxels(self) -> int:
        X, Y, Z = self.grid_shape
        return X * Y * Z

    def frozen_prefix(self, images: torch.Tensor) -> list[torch.Tensor]:
        """images (B, V, 3, H, W) -> the frozen backbone stages' maps, each (B*V, C_l, H_l, W_l)."""
        B, V, C, H, W = images.shape
        return self.backbone.frozen_prefix(images.reshape(B * V, C, H, W))

    def planes(self, images: torch.Tensor | None, ego2img: torch.Tensor,
               prefix: list[torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        """images (B, V, 3, H, W) (or their frozen `prefix`), ego2img (B, V, 4, 4) -> TPV plane maps
        {"xy", "xz", "yz"}: (B, D, rows, cols)."""
        if prefix is None:
            prefix = self.frozen_prefix(images)
        feats = self.fpn(self.backbone.from_prefix(prefix))
        return self.encoder(feats, ego2img)

    def voxel_features(self, images, ego2img, voxel_index: torch.Tensor | None = None,
                       prefix: list[torch.Tensor] | None = None,
                       grid_shape: tuple[int, int, int] | None = None) -> torch.Tensor:
        """(B, N, D) TPV features of every voxel, or (B, M, D) of the voxels `voxel_index` (B, M) only.
        `grid_shape`: read the planes on another grid over the same range (e.g. the GT's 200x200x16 for a
        model trained on 100x100x8: the planes are upsampled bilinearly to it); default the model's grid."""
        planes = self.planes(images, ego2img, prefix)
        shape = tuple(grid_shape) if grid_shape is not None else self.grid_shape
        if voxel_index is None:
            return planes_to_voxels(planes, shape)
        return planes_at_voxels(planes, shape, voxel_index)

    def forward_hidden(self, images: torch.Tensor, ego2img: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """-> h (B, N, Dh), g (B, N, Da): what the ONNX graph computes (last linears folded in later)."""
        h = self.decoder(self.voxel_features(images, ego2img))
        g = self.adapter(self.decoder_out(h))
        return h, g

    def adapt(self, feat: torch.Tensor) -> torch.Tensor:
        """The modality adapter: F_3D (..., C) -> F~_3D (..., C)."""
        return self.adapter_out(self.adapter(feat))

    def forward(self, images: torch.Tensor | None, ego2img: torch.Tensor,
                voxel_index: torch.Tensor | None = None,
                prefix: list[torch.Tensor] | None = None, adapted: bool = True,
                grid_shape: tuple[int, int, int] | None = None) -> dict[str, torch.Tensor]:
        """-> {"feat" (B, N, C), "feat_adapted" (B, N, C), "free_embedding" (C,)}.

        With `voxel_index` (B, M) int64 flat voxel indices (training on a voxel sample), the features
        are (B, M, C) for those voxels and the dict also holds "voxel_index". `adapted=False` leaves
        "feat_adapted" out (training computes F~_3D only where the alignment loss needs it).
        `grid_shape`: the read-out grid (voxel_features); N is then its voxel count."""
        h = self.decoder(self.voxel_features(images, ego2img, voxel_index, prefix, grid_shape))
        feat = self.decoder_out(h)
        out = {"feat": feat, "free_embedding": self.free_embedding}
        if self.free_bias is not None:
            out["free_bias"] = self.free_bias
        if adapted:
            out["feat_adapted"] = self.adapt(feat)
        if voxel_index is not None:
            out["voxel_index"] = voxel_index
        return out
