"""ResNet-50/101 backbones with the user's weights file (`ModelConfig.backbone_weights`): torchvision and
mmdet layouts load, mismatching files are one AgoInputError naming the file, caffe-style weights are
folded into the shared RGB ImageNet preprocessing exactly, and the feature cache is keyed by the file."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.camera import CAMERA_NAMES, Rig
from ago_runtime.geometry.preprocess import Preprocess
from ago_train.model import ModelConfig
from ago_train.model.backbone import CAFFE_MEAN_BGR, RESNET_DEPTHS, ResNetBackbone


def torchvision_state(arch: str = "resnet50", seed: int = 0) -> dict[str, torch.Tensor]:
    """A torchvision-layout ResNet state dict (conv1/bn1/layerN/fc) with random values."""
    torch.manual_seed(seed)
    net = ResNetBackbone(0, RESNET_DEPTHS[arch])
    out = {}
    for k, v in net.state_dict().items():
        k = k.replace("stem.0.", "conv1.").replace("stem.1.", "bn1.")
        if v.is_floating_point():
            v = torch.randn_like(v) * 0.05 + (1.0 if k.endswith(("running_var", "bn1.weight", "bn2.weight")) else 0.0)
            v = v.abs() if k.endswith("running_var") else v
        out[k] = v.clone()
    out["fc.weight"] = torch.randn(1000, 2048)
    out["fc.bias"] = torch.randn(1000)
    return out


def tiny_resnet_config(arch="resnet50", weights=None, **kw) -> ModelConfig:
    cfg = ModelConfig.preset("tiny")
    cfg.backbone, cfg.pretrained, cfg.frozen_stages = arch, weights is not None, 1
    cfg.backbone_weights = None if weights is None else str(weights)
    for k, v in kw.items():
        setattr(cfg, k, v)
    return cfg


@pytest.fixture(scope="module")
def tv_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("w") / "resnet50_tv.pth"
    state = torchvision_state()
    torch.save(state, path)
    return path, state


def test_torchvision_layout_loads_through_the_config(tv_file):
    path, state = tv_file
    model = tiny_resnet_config(weights=path).build()
    bb = model.backbone
    assert torch.equal(bb.stem[0].weight, state["conv1.weight"])
    assert torch.equal(bb.stem[1].running_mean, state["bn1.running_mean"])
    assert torch.equal(bb.layer3[5].conv2.weight, state["layer3.5.conv2.weight"])
    assert torch.equal(bb.layer4[0].downsample[1].running_var, state["layer4.0.downsample.1.running_var"])
    # frozen stages stay frozen (stem + layer1 + layer2), the rest trains; BatchNorm stays in eval mode
    assert not bb.stem[0].weight.requires_grad and not bb.layer2[0].conv1.weight.requires_grad
    assert bb.layer3[0].conv1.weight.requires_grad
    model.train()
    assert not bb.layer3[0].bn1.training
    assert bb.weights_sha256 and bb.weights_file == str(path)
    with torch.no_grad():
        feats = bb(torch.randn(1, 3, 64, 96))
    assert [tuple(f.shape) for f in feats] == [(1, 512, 8, 12), (1, 1024, 4, 6), (1, 2048, 2, 3)]
    assert bb.from_prefix(bb.frozen_prefix(torch.zeros(1, 3, 64, 64)))[0].shape[1] == 512


def test_mmdet_layout_wrapped_in_state_dict_loads(tmp_path, tv_file):
    _, state = tv_file
    mm = {f"backbone.{k}": v for k, v in state.items() if not k.startswith("fc.")}
    mm["neck.lateral_convs.0.conv.weight"] = torch.zeros(256, 512, 1, 1)     # other modules: ignored
    mm["bbox_head.conv_cls.weight"] = torch.zeros(10, 256, 3, 3)
    path = tmp_path / "fcos_like.pth"
    torch.save({"meta": {"epoch": 12}, "state_dict": mm}, path)
    bb = tiny_resnet_config(weights=path).build().backbone
    assert torch.equal(bb.layer1[0].conv1.weight, state["layer1.0.conv1.weight"])
    assert torch.equal(bb.stem[1].weight, state["bn1.weight"])


def _expect_error(path, cfg_arch="resnet50", match=None):
    with pytest.raises(AgoInputError) as e:
        tiny_resnet_config(cfg_arch, weights=path).build()
    assert e.value.path == str(path)
    assert "\n" not in str(e.value)
    if match:
        assert match in str(e.value), str(e.value)
    return str(e.value)


def test_mismatching_files_name_the_file(tmp_path, tv_file):
    _, state = tv_file
    wrong = dict(state)
    wrong["layer2.1.conv2.weight"] = torch.zeros(128, 128, 1, 1)
    torch.save(wrong, tmp_path / "shape.pth")
    _expect_error(tmp_path / "shape.pth", match="layer2.1.conv2.weight [128, 128, 1, 1]")

    missing = {k: v for k, v in state.items() if k != "layer4.2.bn3.running_mean"}
    torch.save(missing, tmp_path / "missing.pth")
    _expect_error(tmp_path / "missing.pth", match="missing layer4.2.bn3.running_mean")

    (tmp_path / "junk.pth").write_bytes(b"this is not a torch file at all\x00\x01" * 10)
    _expect_error(tmp_path / "junk.pth", match="not a state dict file")

    with open(tmp_path / "objects.pkl", "wb") as f:   # a pickle of arbitrary objects: weights_only refuses it
        pickle.dump({"conv1.weight": np.zeros(3)}, f)
    _expect_error(tmp_path / "objects.pkl", match="torch.load(weights_only=True)")

    torch.save({"epoch": 3, "lr": 0.1}, tmp_path / "no_tensors.pth")
    _expect_error(tmp_path / "no_tensors.pth", match="not a ResNet state dict")

    _expect_error(tmp_path / "absent.pth", match="not found")


def test_resnet101_file_into_resnet50_and_dcn_refused(tmp_path, tv_file):
    _, state = tv_file
    deeper = dict(state)
    deeper["layer3.6.conv1.weight"] = torch.zeros(256, 1024, 1, 1)
    torch.save(deeper, tmp_path / "deeper.pth")
    _expect_error(tmp_path / "deeper.pth", match="unexpected keys layer3.6.conv1.weight")

    dcn = {f"backbone.{k}": v for k, v in state.items()}
    dcn["backbone.layer3.0.conv2.conv_offset.weight"] = torch.zeros(27, 256, 3, 3)
    dcn["backbone.layer3.0.conv2.conv_offset.bias"] = torch.zeros(27)
    torch.save({"state_dict": dcn}, tmp_path / "dcn.pth")
    msg = _expect_error(tmp_path / "dcn.pth", match="layer3.0.conv2.conv_offset.bias")
    assert "DCN" in msg


def test_config_refusals():
    with pytest.raises(AgoInputError, match="needs backbone_weights"):
        ModelConfig.from_dict({**ModelConfig().to_dict(), "backbone": "resnet50"})   # pretrained=True by default
    with pytest.raises(AgoInputError, match="are for"):
        ModelConfig.from_dict({**ModelConfig().to_dict(), "backbone_weights": "/x.pth"})   # EfficientNet
    with pytest.raises(AgoInputError, match="backbone_style"):
        ModelConfig.from_dict({**ModelConfig().to_dict(), "backbone": "resnet50", "pretrained": False,
                               "backbone_style": "bgr"})
    ok = ModelConfig.from_dict({**ModelConfig().to_dict(), "backbone": "resnet50", "pretrained": False})
    assert ok.backbone_weights is None


def test_set_override_reaches_the_model_config(tv_file):
    from ago_train.train_config import TrainConfig

    path, _ = tv_file
    cfg = TrainConfig.preset("tiny").with_overrides(["model.backbone=resnet101", f"model.backbone_weights={path}",
                                                     "model.backbone_style=caffe"])
    m = cfg.model
    assert (m.backbone, m.backbone_weights, m.backbone_style) == ("resnet101", str(path), "caffe")


def test_checkpoint_rebuild_does_not_read_the_file(tmp_path):
    cfg = tiny_resnet_config(weights=tmp_path / "gone.pth", backbone_style="caffe")
    bb = cfg.build(load_weights=False).backbone
    assert bb.weights_sha256 is None and bb.style == "caffe"
    assert bb.layer2[0].conv1.stride == (2, 2) and bb.layer2[0].conv2.stride == (1, 1)


def test_caffe_style_is_folded_into_the_rgb_preprocessing_exactly(tmp_path, tv_file):
    """A caffe-style net fed BGR pixels minus CAFFE_MEAN_BGR == ours (folded stem) fed the shared Preprocess."""
    path, state = tv_file
    ours = tiny_resnet_config(weights=path, backbone_style="caffe").build().backbone.eval()
    ref = ResNetBackbone(0, RESNET_DEPTHS["resnet50"], style="caffe").eval()
    ref.load_state_dict({k.replace("conv1.", "stem.0.", 1) if k.startswith("conv1.") else
                         k.replace("bn1.", "stem.1.", 1) if k.startswith("bn1.") else k: v
                         for k, v in state.items() if not k.startswith("fc.")})
    rng = np.random.default_rng(0)
    rgb = {c: rng.integers(0, 256, (64, 64, 3), dtype=np.uint8) for c in CAMERA_NAMES}
    x = torch.from_numpy(Preprocess(64, 64).images(rgb, Rig.nuscenes_like(64, 64)))[:2]                     # (2, 3, 64, 64) RGB ImageNet
    pix = torch.from_numpy(np.stack([rgb[c] for c in CAMERA_NAMES[:2]])).permute(0, 3, 1, 2).double()
    caffe = (pix.flip(1) - torch.tensor(CAFFE_MEAN_BGR, dtype=torch.float64).view(1, 3, 1, 1)).float()
    with torch.no_grad():
        a, b = ours(x), ref(caffe)
    for u, v in zip(a, b):
        assert torch.allclose(u, v, rtol=1e-4, atol=1e-4 * float(v.abs().max())), float((u - v).abs().max())
    # loaded as pytorch style, the same file gives other maps (stride placement and normalisation differ)
    plain = tiny_resnet_config(weights=path).build().backbone.eval()
    with torch.no_grad():
        assert not torch.allclose(plain.frozen_prefix(x)[0], a[0], atol=1e-3)


def test_feature_cache_is_keyed_by_the_weights_file(tmp_path, tv_file):
    from ago_train.feature_cache import backbone_fingerprint

    path, state = tv_file
    other = dict(state)
    other["layer4.0.conv1.weight"] = state["layer4.0.conv1.weight"] + 1.0   # an unfrozen stage only
    torch.save(other, tmp_path / "other.pth")
    pre = Preprocess(96, 64)
    a = tiny_resnet_config(weights=path).build()
    b = tiny_resnet_config(weights=tmp_path / "other.pth").build()
    c = tiny_resnet_config(weights=path, backbone_style="caffe").build()
    fa, fb, fc = (backbone_fingerprint(m, pre) for m in (a, b, c))
    assert len({fa, fb, fc}) == 3
    assert backbone_fingerprint(tiny_resnet_config(weights=path).build(), pre) == fa
