"""`ModelConfig`: every size of the AGO network in one dataclass, with named presets.

Takes: plain values (a JSON-able dict round-trips through `to_dict` / `from_dict`).
Gives: `build()` -> `AGOModel`.

Presets (`ModelConfig.preset(name)`):
- "tiny": tests only (tiny CNN backbone, 20 x 20 x 4 grid, 96 x 64 images, small widths);
- "cpu":  the default (EfficientNet-Lite0 ImageNet backbone, 100 x 100 x 16 grid of 0.8 x 0.8 m voxels
          0.4 m tall - Occ3D's height resolution, so the ground lies in one layer as in the GT -,
          352 x 192 images, a TPV at half the grid's x/y resolution);
- "full": paper-like (200 x 200 x 16 Occ3D grid, 1600 x 928 images, wider TPV and decoder).

The tri-perspective view (TPV) has three planes: plane_xy (top view, tpv_h x tpv_w), plane_xz
(tpv_h x tpv_z) and plane_yz (tpv_w x tpv_z). `tpv_h`, `tpv_w`, `tpv_z` are the plane sizes along
the ego x, y and z axes; None means the grid's size along that axis. Coarser planes are upsampled
to the grid (bilinear) before the planes are summed into voxels.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.grid import Grid

BACKBONES = ("efficientnet_lite0", "resnet50", "resnet101", "tiny_cnn")
RESNETS = ("resnet50", "resnet101")   # weights only from the user's file: backbone_weights
TPV_LAYOUTS = ("canvas", "reference")   # ago_train/model/tpv_canvas.py, tpv.py


CPU_GRID_SHAPE = (100, 100, 16)   # the cpu preset's grid (0.8 x 0.8 x 0.4 m); `ago pseudo-labels --grid` default


def _default_grid() -> dict:
    return Grid.with_shape(CPU_GRID_SHAPE).to_dict()


@dataclass
class ModelConfig:
    # --- geometry / input
    grid: dict = field(default_factory=_default_grid)  # ago_runtime.geometry.grid.Grid.to_dict()
    image_width: int = 352   # = ago_runtime.geometry.preprocess.Preprocess.width
    image_height: int = 192  # = ago_runtime.geometry.preprocess.Preprocess.height
    num_cameras: int = 6
    # --- image backbone + FPN
    backbone: str = "efficientnet_lite0"  # "efficientnet_lite0" | "resnet50" | "resnet101" | "tiny_cnn"
    pretrained: bool = True               # ImageNet weights (EfficientNet-Lite0: bundled; ResNet: backbone_weights)
    backbone_weights: str | None = None   # ResNet only: torchvision/mmdet state dict file (docs/model.md)
    backbone_style: str = "pytorch"       # ResNet only: "pytorch" (torchvision) | "caffe" (mmdet caffe, e.g. FCOS3D)
    frozen_stages: int = 1                # backbone stages kept frozen: 0 none, 1 up to stride 8, 2 up to 16, 3 all
    # --- TPV encoder
    tpv_dim: int = 64
    tpv_h: int | None = 50      # plane size along ego x (None = grid X)
    tpv_w: int | None = 50      # plane size along ego y (None = grid Y)
    tpv_z: int | None = None    # plane size along ego z (None = grid Z)
    num_points_in_pillar: int = 4        # 3-D reference points per top-plane (xy) query, along z
    num_points_in_pillar_side: int = 8   # reference points per side-plane (xz, yz) query, along y / x
    num_sampling_offsets: int = 1        # learned image sampling offsets per reference point (per head, level)
    cameras_per_query: int = 2           # plane_xy queries read their k most visible cameras (>= 6: all)
    cameras_per_query_side: int = 4      # the same for plane_xz / plane_yz queries (long pillars)
    num_cross_view_points: int = 4       # points a query samples along the shared axis in each other plane
    num_self_points: int = 4             # points a query samples around itself in its own plane
    num_heads: int = 4
    num_layers: int = 2
    tpv_layout: str = "canvas"           # how the TPV arithmetic runs (same function): "canvas" | "reference"
    query_pos: bool = False              # add the learnt plane queries (each cell's own embedding: its position)
                                         # to the input of every encoder layer after the first, as TPVFormer
                                         # adds its positional encoding in every layer
    ffn_dim: int = 128
    # --- decoder + adapter
    hidden_dim: int = 128      # Dh, decoder hidden width
    decoder_layers: int = 1    # hidden layers (softplus) before `decoder_out`
    embed_dim: int = 384       # C, the text embedding width (all-MiniLM-L6-v2)
    free_bias: bool = False    # a learnt scalar added to the free score (F_3D . free_embedding + b), started at
                               # the training data's prior log-odds of free (ago_train/trainer.py)
    adapter_depth: int = 2     # 1..4 linear layers in the modality adapter (2 = paper)
    adapter_hidden: int = 384

    # ---------------------------------------------------------------- helpers
    def grid_obj(self) -> Grid:
        return Grid.from_dict(self.grid)

    def tpv_shape(self) -> tuple[int, int, int]:
        """(TPV size along x, along y, along z)."""
        X, Y, Z = self.grid_obj().shape
        return (self.tpv_h or X, self.tpv_w or Y, self.tpv_z or Z)

    def validate(self, source: str | None = None) -> None:
        if self.backbone not in BACKBONES:
            raise AgoInputError(source, f"unknown backbone {self.backbone!r}; expected one of {BACKBONES}")
        if self.backbone_weights is not None and not (isinstance(self.backbone_weights, str) and self.backbone_weights):
            raise AgoInputError(source, f"backbone_weights must be a file path or null, got {self.backbone_weights!r}")
        if self.backbone_style not in ("pytorch", "caffe"):
            raise AgoInputError(source, f"backbone_style must be 'pytorch' or 'caffe', got {self.backbone_style!r}")
        if self.backbone not in RESNETS and (self.backbone_weights or self.backbone_style != "pytorch"):
            raise AgoInputError(source, f"backbone_weights / backbone_style are for {RESNETS}, not {self.backbone!r}")
        if self.backbone in RESNETS and self.pretrained and not self.backbone_weights:
            raise AgoInputError(source, f"{self.backbone} with pretrained=true needs backbone_weights=PATH (no ResNet "
                                        "weights ship with ago and nothing is downloaded); or set pretrained=false")
        if not 0 <= self.frozen_stages <= 3:
            raise AgoInputError(source, f"frozen_stages must be 0..3, got {self.frozen_stages}")
        if not 1 <= self.adapter_depth <= 4:
            raise AgoInputError(source, f"adapter_depth must be 1..4, got {self.adapter_depth}")
        if self.tpv_layout not in TPV_LAYOUTS:
            raise AgoInputError(source, f"unknown tpv_layout {self.tpv_layout!r}; expected one of {TPV_LAYOUTS}")
        if self.tpv_dim % self.num_heads:
            raise AgoInputError(source, f"tpv_dim {self.tpv_dim} is not divisible by num_heads {self.num_heads}")
        if self.image_width % 32 or self.image_height % 32:
            raise AgoInputError(source, f"image size {self.image_width}x{self.image_height} must be a multiple of 32")
        X, Y, Z = self.grid_obj().shape
        h, w, z = self.tpv_shape()
        if h > X or w > Y or z > Z:
            raise AgoInputError(source, f"TPV {h}x{w}x{z} is finer than the grid {X}x{Y}x{Z}")
        for name in ("num_points_in_pillar", "num_points_in_pillar_side", "num_sampling_offsets",
                     "num_cross_view_points", "num_self_points", "num_layers", "decoder_layers",
                     "cameras_per_query", "cameras_per_query_side"):
            if getattr(self, name) < 1:
                raise AgoInputError(source, f"{name} must be >= 1")

    def build(self, load_weights: bool = True) -> "AGOModel":  # noqa: F821
        """load_weights=False: leave a ResNet's backbone_weights file unread (every weight comes from a checkpoint)."""
        from .ago_model import AGOModel
        from .backbone import configure_backbone

        model = AGOModel(self)
        configure_backbone(model.backbone, self, load_weights)
        return model

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict, source: str | None = None) -> "ModelConfig":
        from ..config_checks import check_model_config

        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise AgoInputError(source, f"unknown model config keys {unknown}")
        cfg = cls(**d)
        check_model_config(cfg, source)   # types and ranges first: validate() computes with them
        cfg.validate(source)
        return cfg

    @classmethod
    def preset(cls, name: str) -> "ModelConfig":
        if name == "cpu":
            return cls()
        if name == "tiny":
            return cls(
                grid=Grid.with_shape((20, 20, 4)).to_dict(), image_width=96, image_height=64,
                backbone="tiny_cnn", pretrained=False, frozen_stages=0, tpv_dim=32, tpv_h=None, tpv_w=None,
                num_points_in_pillar=4, num_points_in_pillar_side=4, num_sampling_offsets=1,
                num_cross_view_points=2, num_self_points=2, num_heads=2, num_layers=1, ffn_dim=64,
                hidden_dim=32, embed_dim=384, adapter_depth=2, adapter_hidden=64,
            )
        if name == "full":
            return cls(
                grid=Grid.occ3d().to_dict(), image_width=1600, image_height=928,
                backbone="efficientnet_lite0", pretrained=True, frozen_stages=1, tpv_dim=128,
                tpv_h=100, tpv_w=100, tpv_z=16, num_points_in_pillar=4, num_points_in_pillar_side=32,
                num_sampling_offsets=2, num_cross_view_points=8, num_self_points=4, num_heads=8,
                num_layers=3, ffn_dim=256, hidden_dim=256, decoder_layers=2, adapter_hidden=384, free_bias=True,
            )
        raise AgoInputError(None, f"unknown model preset {name!r}; expected tiny, cpu or full")


PRESETS = ("tiny", "cpu", "full")


def min_model_grid() -> tuple[int, int, int]:
    """The smallest model grid of ago's presets, per axis: tiny's 20x20x4 (its TPV planes are its grid, 20x20,
    20x4, 20x4; cpu's planes are 50x50 on the Occ3D 200x200x16 grid, full's 100x100x16 on the same grid, and
    ModelConfig.validate refuses a grid coarser than its planes)."""
    shapes = [ModelConfig.preset(name).grid_obj().shape for name in PRESETS]
    return tuple(min(s[axis] for s in shapes) for axis in range(3))


def check_min_grid(shape, option: str) -> None:
    """Refuse a labels grid (`ago synth`'s GT, `ago pseudo-labels`) coarser along an axis than min_model_grid():
    a model trains on pseudo-labels of its own grid, and a GT is scored only at an integer multiple of the
    model's grid (ago_train/evaluate.py, _grid_factors), so a coarser grid serves no preset model."""
    low = min_model_grid()
    if any(n < m for n, m in zip(shape, low)):
        raise AgoInputError(option, f"{'x'.join(map(str, shape))} is coarser than the smallest model grid "
                                    f"{'x'.join(map(str, low))} along an axis (the tiny preset's: its TPV planes are its "
                                    "grid; a GT must be a whole multiple of a model grid to be scored)")
