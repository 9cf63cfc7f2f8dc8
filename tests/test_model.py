"""AGOModel: config/presets, the forward contract, backbone weights, camera projection, ONNX export,
text scoring and the open-world identifier."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from ago_runtime.geometry.camera import Rig
from ago_runtime.errors import AgoInputError
from ago_train.model.config import ModelConfig
from ago_train.model.text_logits import NO_PHRASE_SCORE, class_logits, decide
from ago_train.model.tpv import ImageCrossAttention, project_to_cameras

# static shapes are read as Python ints on purpose while tracing (fixed-size ONNX graph)
pytestmark = pytest.mark.filterwarnings("ignore::torch.jit.TracerWarning")


def _inputs(cfg: ModelConfig, batch: int = 1, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    images = torch.randn(batch, 6, 3, cfg.image_height, cfg.image_width, generator=g)
    ego2img = torch.from_numpy(Rig.nuscenes_like(cfg.image_width, cfg.image_height).ego2img())
    return images, ego2img[None].repeat(batch, 1, 1, 1)


@pytest.fixture(scope="module")
def tiny():
    torch.manual_seed(0)
    cfg = ModelConfig.preset("tiny")
    return cfg, cfg.build().eval()



@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Tiny tensors: one thread is faster than two and does not fight parallel test workers."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)

# ------------------------------------------------------------------ config
def test_config_round_trip_and_validation():
    for name in ("tiny", "cpu", "full"):
        cfg = ModelConfig.preset(name)
        cfg.validate()
        assert ModelConfig.from_dict(cfg.to_dict()) == cfg
    assert ModelConfig.preset("full").grid_obj().shape == (200, 200, 16)
    assert ModelConfig().grid_obj().shape == (100, 100, 16)
    with pytest.raises(AgoInputError):
        ModelConfig.from_dict({**ModelConfig().to_dict(), "backbone": "vgg"})
    with pytest.raises(AgoInputError):
        ModelConfig.from_dict({**ModelConfig().to_dict(), "no_such_key": 1})
    with pytest.raises(AgoInputError):
        ModelConfig.preset("huge")


# ------------------------------------------------------------------ forward contract
def test_forward_contract_tiny(tiny):
    cfg, model = tiny
    images, ego2img = _inputs(cfg, batch=2)
    X, Y, Z = cfg.grid_obj().shape
    assert isinstance(model.decoder_out, nn.Linear) and model.decoder_out.bias is not None
    assert isinstance(model.adapter_out, nn.Linear) and model.adapter_out.bias is not None
    assert model.free_embedding.shape == (cfg.embed_dim,)
    with torch.no_grad():
        h, g = model.forward_hidden(images, ego2img)
        out = model(images, ego2img)
    assert h.shape == (2, X * Y * Z, cfg.hidden_dim)
    assert g.shape == (2, X * Y * Z, cfg.adapter_hidden)
    assert out["feat"].shape == out["feat_adapted"].shape == (2, X * Y * Z, cfg.embed_dim)
    torch.testing.assert_close(out["feat"], model.decoder_out(h))
    torch.testing.assert_close(out["feat_adapted"], model.adapter_out(g))
    # the two frames differ in their images only: their features must differ
    assert not torch.allclose(out["feat"][0], out["feat"][1])
    # each frame of a batch is computed as if alone
    with torch.no_grad():
        alone = model(images[1:], ego2img[1:])
    torch.testing.assert_close(alone["feat"][0], out["feat"][1], rtol=1e-4, atol=1e-5)


def test_adapter_depths():
    images, ego2img = _inputs(ModelConfig.preset("tiny"))
    for depth in (1, 2, 3, 4):
        cfg = ModelConfig.preset("tiny")
        cfg.adapter_depth = depth
        model = cfg.build().eval()
        linears = [m for m in model.adapter.modules() if isinstance(m, nn.Linear)]
        assert len(linears) == depth - 1
        with torch.no_grad():
            h, g = model.forward_hidden(images, ego2img)
        if depth == 1:
            torch.testing.assert_close(g, model.decoder_out(h))   # g = F_3D
        else:
            assert g.shape[-1] == cfg.adapter_hidden and bool((g > 0).all())  # softplus output


def test_voxel_sample_matches_full_grid(tiny):
    cfg, model = tiny
    images, ego2img = _inputs(cfg)
    idx = torch.randperm(model.num_voxels, generator=torch.Generator().manual_seed(1))[:100][None]
    with torch.no_grad():
        full = model(images, ego2img)
        part = model(images, ego2img, voxel_index=idx)
    torch.testing.assert_close(part["feat"][0], full["feat"][0, idx[0]], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(part["feat_adapted"][0], full["feat_adapted"][0, idx[0]], rtol=1e-5, atol=1e-5)
    assert torch.equal(part["voxel_index"], idx)


def test_coarse_tpv_is_upsampled_to_the_grid():
    cfg = ModelConfig.preset("tiny")
    cfg.tpv_h, cfg.tpv_w, cfg.tpv_z = 10, 10, 2
    model = cfg.build().eval()
    images, ego2img = _inputs(cfg)
    with torch.no_grad():
        planes = model.planes(images, ego2img)
        h, _ = model.forward_hidden(images, ego2img)
    assert planes["xy"].shape[-2:] == (10, 10) and planes["xz"].shape[-2:] == (10, 2)
    assert h.shape[1] == 20 * 20 * 4


def test_cpu_preset_shapes():
    cfg = ModelConfig.preset("cpu")
    cfg.pretrained = False
    model = cfg.build().eval()
    images, ego2img = _inputs(cfg)
    with torch.no_grad():
        h, g = model.forward_hidden(images, ego2img)
    assert h.shape == (1, 100 * 100 * 16, cfg.hidden_dim) and g.shape == (1, 160000, cfg.adapter_hidden)
    assert torch.isfinite(h).all() and torch.isfinite(g).all()


# ------------------------------------------------------------------ backbone weights
def test_efficientnet_imagenet_weights_load():
    from ago_train.model.backbone import EfficientNetLite0Backbone, efficientnet_lite0_weights_path

    state = torch.load(efficientnet_lite0_weights_path(), map_location="cpu", weights_only=True)
    bb = EfficientNetLite0Backbone(192, 352, pretrained=True, frozen_stages=1)
    torch.testing.assert_close(bb.stem[0].weight, state["_conv_stem.weight"], rtol=0, atol=0)
    torch.testing.assert_close(bb.stem[1].running_var, state["_bn0.running_var"], rtol=0, atol=0)
    torch.testing.assert_close(bb.stage16[0]._depthwise_conv.weight, state["_blocks.5._depthwise_conv.weight"],
                               rtol=0, atol=0)
    torch.testing.assert_close(bb.stage32[-1]._project_conv.weight, state["_blocks.15._project_conv.weight"],
                               rtol=0, atol=0)
    assert not bb.stem[0].weight.requires_grad and bb.stage32[-1]._project_conv.weight.requires_grad
    random = EfficientNetLite0Backbone(192, 352, pretrained=False)
    assert not torch.equal(random.stem[0].weight, state["_conv_stem.weight"])
    bb.train()
    assert not bb.stem[1].training  # BatchNorm stays in eval mode
    with torch.no_grad():
        feats = bb(torch.randn(2, 3, 192, 352))
    assert [tuple(f.shape) for f in feats] == [(2, 40, 24, 44), (2, 112, 12, 22), (2, 320, 6, 11)]


def test_resnet101_option_strides():
    from ago_train.model.backbone import ResNet101Backbone

    bb = ResNet101Backbone(frozen_stages=1).eval()
    assert sum(p.numel() for p in bb.parameters()) > 40e6          # ResNet-101 sized (no fc)
    with torch.no_grad():
        feats = bb(torch.randn(1, 3, 64, 96))
    assert [tuple(f.shape) for f in feats] == [(1, 512, 8, 12), (1, 1024, 4, 6), (1, 2048, 2, 3)]


# ------------------------------------------------------------------ geometry
def test_projection_matches_camera_project():
    rig = Rig.nuscenes_like(96, 64)
    pts = torch.tensor([[[10.0, 0.5, 1.0], [5.0, 3.0, 0.2]], [[-8.0, 1.0, 1.5], [0.0, 9.0, 0.5]]])  # (Q=2, P=2, 3)
    uv, mask = project_to_cameras(pts, torch.from_numpy(rig.ego2img())[None], 96, 64)
    for v, cam in enumerate(rig):
        puv, _, ok = cam.project(pts.reshape(-1, 3).numpy())
        np.testing.assert_array_equal(mask[0, v].reshape(-1).numpy() > 0, ok)
        norm = np.stack([puv[:, 0] / 96 * 2 - 1, puv[:, 1] / 64 * 2 - 1], -1)
        np.testing.assert_allclose(uv[0, v].reshape(-1, 2).numpy()[ok], norm[ok], atol=1e-4)
    assert mask[0, 0, 0, 0] == 1  # 10 m ahead is seen by CAM_FRONT


def test_feature_planted_at_a_pixel_reaches_the_voxel_in_front_of_it():
    """One FPN pixel of CAM_FRONT carries a feature; only plane_xy queries whose pillar projects onto
    (or right next to) that pixel read it."""
    cfg = ModelConfig.preset("tiny")
    model = cfg.build()
    enc = model.encoder
    W, H = cfg.image_width, cfg.image_height
    ego2img = torch.from_numpy(Rig.nuscenes_like(W, H).ego2img())[None]
    pillars = enc.pillar_xy                                             # (Q, P, 3)
    uv, mask = project_to_cameras(pillars, ego2img, W, H)
    count = mask.amax(-1).sum(1)
    X, Y, _ = cfg.tpv_shape()
    xs, ys = enc.geometry.centres[0], enc.geometry.centres[1]
    target = int(np.argmin(np.abs(xs - 10.0))) * Y + int(np.argmin(np.abs(ys - 0.0)))   # ~10 m ahead
    k = 1                                                              # second pillar point
    assert mask[0, 0, target, k] == 1
    stride, D = 8, cfg.tpv_dim
    fh, fw = H // stride, W // stride
    px = ((uv[0, 0, target, k] + 1) / 2 * torch.tensor([fw, fh])).floor().long()  # feature pixel hit
    value = torch.zeros(6, D, fh, fw)
    value[0, :, px[1], px[0]] = 1.0
    ica = ImageCrossAttention(D, cfg.num_heads, 1, cfg.num_points_in_pillar, 1)
    with torch.no_grad():
        ica.sampling_offsets.bias.zero_()
        ica.output_proj.weight.copy_(torch.eye(D))
        ica.output_proj.bias.zero_()
        heads = cfg.num_heads
        out = ica(torch.zeros(1, X * Y, D), [value.reshape(6 * heads, D // heads, fh, fw)], uv, mask, count)
    read = out[0].abs().sum(-1)                                       # (Q,)
    assert read[target] > 0.01
    # queries none of whose pillar points lands within one feature pixel of the planted one read nothing
    pix = (uv[0, 0] + 1) / 2 * torch.tensor([fw, fh])                 # (Q, P, 2) feature-pixel coords
    centre = px.float() + 0.5
    near = (((pix - centre).abs() < 1.0).all(-1) & (mask[0, 0] > 0)).any(-1)
    assert near[target]
    assert torch.all(read[~near] == 0)
    assert int(near.sum()) < X * Y // 4


def test_top_k_camera_atlas_equals_dense_cameras():
    """Reading each query's k most visible cameras from the atlas gives the dense six-camera result
    (the nuScenes-like rig sees a vertical pillar with <= 2 cameras and a side pillar with <= 4)."""
    images, ego2img = _inputs(ModelConfig.preset("tiny"), seed=5)
    outs = []
    for k_top, k_side in ((6, 6), (2, 4)):
        torch.manual_seed(0)
        cfg = ModelConfig.preset("tiny")
        cfg.cameras_per_query, cfg.cameras_per_query_side, cfg.num_sampling_offsets = k_top, k_side, 2
        model = cfg.build().eval()
        with torch.no_grad():  # non-trivial offsets / weights so samples leave the reference points
            for m in model.modules():
                if isinstance(m, ImageCrossAttention):
                    m.sampling_offsets.weight.normal_(0, 0.5, generator=torch.Generator().manual_seed(1))
                    m.attention_weights.weight.normal_(0, 0.5, generator=torch.Generator().manual_seed(2))
            outs.append(model.forward_hidden(images, ego2img)[0])
    torch.testing.assert_close(outs[1], outs[0], rtol=1e-5, atol=1e-5)
    assert outs[0].abs().max() > 0.1


@pytest.mark.parametrize("k_top,k_side,offsets", [(2, 4, 1), (6, 6, 2), (3, 2, 2)])
def test_canvas_layout_equals_reference_values_and_gradients(k_top, k_side, offsets):
    """The canvas layout (tpv_canvas.py, the default training path and the export's), in its static
    form (what the export traces) and its compact form (valid samples only: training), computes the
    reference layout's planes and the same gradients for every parameter and the FPN maps, on a
    batch of two frames with different rigs, with offsets large enough to leave the maps."""
    torch.manual_seed(0)
    cfg = ModelConfig.preset("tiny")
    cfg.cameras_per_query, cfg.cameras_per_query_side, cfg.num_sampling_offsets = k_top, k_side, offsets
    model = cfg.build()
    with torch.no_grad():
        for name, p in model.encoder.named_parameters():
            if "sampling_offsets" in name:
                p.normal_(0, 3.0, generator=torch.Generator().manual_seed(1))
            elif "attention_weights" in name:
                p.normal_(0, 0.5, generator=torch.Generator().manual_seed(2))
    images, _ = _inputs(cfg, batch=2, seed=7)
    rigs = [Rig.nuscenes_like(cfg.image_width, cfg.image_height), Rig.nuscenes_like(1600, 900)]
    from ago_runtime.geometry.preprocess import Preprocess
    ego2img = torch.stack([torch.from_numpy(rigs[0].ego2img()),
                           torch.from_numpy(Preprocess(cfg.image_width, cfg.image_height).ego2img(rigs[1]))])
    with torch.no_grad():
        feats0 = model.fpn(model.backbone(images.flatten(0, 1)))
    results = {}
    for layout in ("reference", "canvas", "canvas, static", "canvas, compact"):
        model.cfg.tpv_layout = layout.split(",")[0]
        model.zero_grad(set_to_none=True)
        feats = [f.clone().requires_grad_(True) for f in feats0]
        if layout == "canvas, static":
            planes = model.encoder.forward_canvas(feats, ego2img, compact=False)
        elif layout == "canvas, compact":
            planes = model.encoder.forward_canvas(feats, ego2img, compact=True)
        else:
            planes = model.encoder(feats, ego2img)   # canvas: compact, as in training (no trace running)
        g = torch.Generator().manual_seed(3)
        loss = sum((planes[p] * torch.randn(planes[p].shape, generator=g)).sum() for p in ("xy", "xz", "yz"))
        loss.backward()
        grads = {n: p.grad.clone() for n, p in model.encoder.named_parameters() if p.grad is not None}
        results[layout] = (planes, grads, [f.grad.clone() for f in feats])
    pr, gr, fr = results["reference"]
    for layout in ("canvas", "canvas, static", "canvas, compact"):
        pc, gc, fc = results[layout]
        for p in pr:
            torch.testing.assert_close(pc[p], pr[p], rtol=1e-4, atol=2e-5)
        assert set(gc) == set(gr) and len(gr) > 20
        for n in gr:
            torch.testing.assert_close(gc[n], gr[n], rtol=1e-3, atol=1e-4, msg=f"{layout}: {n}")
        for a, b in zip(fc, fr):
            torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4)
    assert max(float(g.abs().max()) for n, g in gr.items() if "sampling_offsets" in n) > 1e-3
    assert not torch.allclose(pr["xy"][0], pr["xy"][1])          # the two frames differ


def test_tpv_layout_is_checked():
    cfg = ModelConfig.preset("tiny")
    cfg.tpv_layout = "fast"
    with pytest.raises(AgoInputError, match="tpv_layout"):
        cfg.validate()


# ------------------------------------------------------------------ ONNX
def test_onnx_export_parity_without_nonzero(tiny, tmp_path):
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    cfg, model = tiny

    class Hidden(nn.Module):
        def __init__(self, m):
            super().__init__()
            self.m = m

        def forward(self, images, ego2img):
            return self.m.forward_hidden(images, ego2img)

    wrapper = Hidden(model).eval()
    images, ego2img = _inputs(cfg, seed=3)
    path = tmp_path / "hidden.onnx"
    torch.onnx.export(wrapper, (images, ego2img), str(path), opset_version=17, dynamo=False,
                      input_names=["images", "ego2img"], output_names=["h", "g"])
    graph = onnx.load(str(path))
    ops = {n.op_type for n in graph.graph.node}
    assert "NonZero" not in ops and "GridSample" in ops
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    # a different frame and a moved rig than the export sample: ego2img is a real input
    images2, _ = _inputs(cfg, seed=4)
    e2 = ego2img.clone()
    e2[..., :3, 3] += torch.tensor([3.0, -2.0, 0.5])
    h_ort, g_ort = sess.run(None, {"images": images2.numpy(), "ego2img": e2.numpy()})
    with torch.no_grad():
        h, g = model.forward_hidden(images2, e2)
    assert np.abs(h_ort - h.numpy()).max() <= 1e-4 * max(1.0, float(h.abs().max()))
    assert np.abs(g_ort - g.numpy()).max() <= 1e-4 * max(1.0, float(g.abs().max()))


# ------------------------------------------------------------------ scoring
def test_class_logits_order_and_max_over_phrases():
    phrase_class = torch.tensor([2, 0, 2, 1, 2])
    g = torch.Generator().manual_seed(0)
    feat = torch.randn(2, 7, 8, generator=g)
    text = torch.randn(5, 8, generator=g)
    free = torch.randn(8, generator=g)
    noise = torch.randn(3, 8, generator=g)
    logits = class_logits(feat, text, phrase_class, 4, free, noise)
    assert logits.shape == (2, 7, 4 + 1 + 3)
    s = feat @ text.T
    torch.testing.assert_close(logits[..., 0], s[..., 1])
    torch.testing.assert_close(logits[..., 1], s[..., 3])
    torch.testing.assert_close(logits[..., 2], torch.maximum(torch.maximum(s[..., 0], s[..., 2]), s[..., 4]))
    assert torch.all(logits[..., 3] == NO_PHRASE_SCORE)               # class 3 has no phrase
    torch.testing.assert_close(logits[..., 4], feat @ free)
    torch.testing.assert_close(logits[..., 5:], feat @ noise.T)
    assert class_logits(feat, text, phrase_class, 4, free, None).shape[-1] == 5
    # the gradient of a class column reaches only the phrase that is its max, voxel by voxel
    text_g = text.clone().requires_grad_(True)
    class_logits(feat, text_g, phrase_class, 4, free, None)[..., 2].sum().backward()
    winner = torch.stack([s[..., 0], s[..., 2], s[..., 4]], -1).argmax(-1)          # (2, 7) in 0..2
    expected = torch.zeros_like(text)
    for j, p in enumerate([0, 2, 4]):
        expected[p] = (feat * (winner == j)[..., None]).sum((0, 1))
    torch.testing.assert_close(text_g.grad, expected)


def test_decide_modes():
    K = 2
    # voxel 0: main confident (class 0), adapted flat; voxel 1: main flat, adapted confident (class 1)
    main = torch.tensor([[5.0, 0.0, 0.0, 9.0], [0.0, 0.0, 0.0, 0.0]])        # last column: a noise word
    adapted = torch.tensor([[0.0, 0.1, 0.0, 0.0], [0.0, 6.0, 0.0, 0.0]])
    d = decide(main, adapted, "min-entropy", num_classes=K)
    assert d.label.tolist() == [0, 1] and d.branch.tolist() == [0, 1]          # noise column ignored
    assert torch.all(d.entropy < np.log(3))
    assert torch.equal(d.entropy, torch.where(d.branch == 1, d.entropy_adapted, d.entropy_main))
    d = decide(main, adapted, "max-conf", num_classes=K)
    assert d.label.tolist() == [0, 1] and d.branch.tolist() == [0, 1]
    d = decide(main, adapted, "none", num_classes=K)
    assert d.branch.tolist() == [0, 0] and d.label[0] == 0
    # "none" needs no adapted logits and gives the main branch's argmax over [K classes + free]
    alone = decide(main, None, "none", num_classes=K)
    assert torch.equal(alone.label, d.label) and alone.entropy_adapted is None
    assert torch.equal(alone.label, main[:, : K + 1].argmax(-1))
    with pytest.raises(ValueError, match="reads the adapted branch"):
        decide(main, None, "min-entropy", num_classes=K)
    with pytest.raises(ValueError):
        decide(main, adapted, "vote", num_classes=K)
    # a voxel the main branch calls free stays free, however sure the adapted branch is
    free_main = torch.tensor([[0.0, 0.0, 4.0, 0.0]])
    sure = torch.tensor([[0.0, 9.0, 0.0, 0.0]])
    for mode in ("min-entropy", "max-conf", "adapted"):
        d = decide(free_main, sure, mode, num_classes=K)
        assert d.label.tolist() == [K] and d.branch.tolist() == [0]
    # the scales are temperatures: a flat-looking adapted branch wins once its scale is large enough
    soft = torch.tensor([[0.0, 0.3, -9.0, 0.0]])
    firm = torch.tensor([[2.0, 0.0, -9.0, 0.0]])
    assert decide(firm, soft, "min-entropy", K).branch.tolist() == [0]
    d = decide(firm, soft, "min-entropy", K, scales=(1.0, 20.0))
    assert d.branch.tolist() == [1] and d.label.tolist() == [1]
