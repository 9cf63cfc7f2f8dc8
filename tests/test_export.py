"""`ago export`: the real tiny-preset model -> bundle; ONNX checks, parity, atomic failure, int8."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import tiny_town

from ago_runtime.geometry.camera import CAMERA_NAMES, Rig

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from ago_export.export import export_bundle, load_model  # noqa: E402
from ago_export.graphs import LogSigmoidSoftplus, export_activations, interpolation_matrix  # noqa: E402
from ago_export.parity import Tolerance, reference_labels  # noqa: E402
from ago_export.testing import random_checkpoint  # noqa: E402
from ago_runtime.predict.bundle import Bundle  # noqa: E402
from ago_runtime.errors import AgoInputError  # noqa: E402
from ago_runtime.predict.predictor import Predictor  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHARED_SAMPLE = REPO.parent / "shared" / "data" / "nuscenes-sample"


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    root = tmp_path_factory.mktemp("export")
    os.environ["AGO_CACHE_DIR"] = str(root / "cache")
    ckpt = random_checkpoint(root / "tiny.pt", "tiny", prompts="cw", seed=0)
    bundle = root / "bundle"
    town = tiny_town(root / "town")   # the int8 graph's calibration frames (a random checkpoint records none)
    meta = export_bundle(ckpt, bundle, int8=True, bank_prompts=["ow"], log=lambda s: None, calibration_data=town)
    return {"root": root, "ckpt": ckpt, "bundle": bundle, "meta": meta}


def test_plane_upsampling_matrices_are_bilinear_interpolation():
    # planes.onnx upsamples channels last with two matrix products; they must be F.interpolate's bilinear
    import torch
    import torch.nn.functional as F

    g = torch.Generator().manual_seed(0)
    for (r, c), (R, C) in [((100, 100), (200, 200)), ((100, 16), (200, 16)), ((7, 5), (20, 11)), ((10, 9), (6, 4)),
                           ((3, 3), (3, 3))]:
        m = torch.randn(1, 4, r, c, generator=g)
        ref = F.interpolate(m, size=(R, C), mode="bilinear", align_corners=False)[0].permute(1, 2, 0)
        a, b = interpolation_matrix(r, R), interpolation_matrix(c, C)
        got = torch.matmul(b, torch.matmul(a, m[0].permute(1, 2, 0).reshape(r, -1)).reshape(R, c, -1))
        assert got.shape == (R, C, 4)
        torch.testing.assert_close(got, ref, atol=1e-5, rtol=1e-5)
        assert torch.allclose(a.sum(1), torch.ones(R))          # two taps whose weights sum to one
    assert torch.equal(interpolation_matrix(5, 5), torch.eye(5))


def test_bundle_is_self_describing(env):
    meta = json.loads((env["bundle"] / "bundle.json").read_text())
    assert meta["format_version"] == 5
    assert {"planes", "voxels_0", "heads"} <= set(meta["files"]) and "voxels_1" not in meta["files"]
    assert [st["branch"] for st in meta["voxel_stages"]] == ["adapted"]     # tiny: decoder 1 layer, adapter 2
    assert (meta["hidden_dim"], meta["adapted_dim"]) == tuple(meta["voxel_stages"][0][k] for k in ("input_dim", "output_dim"))
    assert not (env["bundle"] / "voxels_1.onnx").exists()
    assert meta["grid"]["shape"] == [20, 20, 4]
    assert [c["name"] for c in meta["label_space"]["classes"]][:3] == ["others", "barrier", "bicycle"]
    assert meta["label_space"]["classes"][4]["table_ids"] == [4]          # car
    assert meta["preprocess"]["width"] == 96 and meta["preprocess"]["height"] == 64
    assert [c["name"] for c in meta["rig"]["cameras"]] == list(CAMERA_NAMES)
    assert all((c["width"], c["height"]) == (96, 64) for c in meta["rig"]["cameras"])
    assert len(meta["training_rig"]["cameras"]) == 6
    assert meta["text_encoder"]["dim"] == 384 and meta["text_encoder"]["id"]
    assert set(meta["banks"]) == {"train", "ow"}
    for entry in meta["files"].values():
        assert (env["bundle"] / entry["path"]).stat().st_size == entry["size"]
    # no temp folders left next to the bundle
    assert not [p for p in env["root"].iterdir() if p.name.startswith(".bundle")]


def test_onnx_files_check(env):
    ios = {"planes": (["images", "ego2img"], ["plane_xy", "plane_xz", "plane_yz"]),
           "voxels_0": (["x"], ["y"])}       # a stage holds its layer only: no bank input, no bank product
    for name, (inputs, outputs) in ios.items():
        path = env["bundle"] / f"{name}.onnx"
        onnx.checker.check_model(str(path), full_check=True)
        model = onnx.load(str(path))
        assert [i.name for i in model.graph.input] == inputs
        assert [o.name for o in model.graph.output] == outputs
        ops = {n.op_type for n in model.graph.node}
        assert "Softplus" not in ops
        # planes.onnx samples only what the cameras see, as training does (ExportTPV): its one data-dependent shape
        assert ("NonZero" in ops) == (name == "planes")
    assert {n.op_type for n in onnx.load(str(env["bundle"] / "voxels_0.onnx")).graph.node} <= {"MatMul", "Add", "Gemm"}


def test_split_encoder_slabs_equal_the_torch_model_voxel_by_voxel(env):
    """Any slab size gives the same h, g as the torch model's forward_hidden on the whole grid."""
    import torch

    from ago_export.export import load_model
    from ago_runtime.predict.bundle import Bundle
    from ago_runtime.predict.encoder import open_encoder

    model, _ckpt, cfg = load_model(env["ckpt"])
    b = Bundle.load(env["bundle"])
    rng = np.random.default_rng(0)
    x = rng.normal(size=(1, 6, 3, cfg.image_height, cfg.image_width)).astype(np.float32)
    m = np.asarray(b.preprocess.ego2img(b.rig))[None].astype(np.float32)
    with torch.no_grad():
        h_t, g_t = model.forward_hidden(torch.from_numpy(x), torch.from_numpy(m))
    for slab_voxels in (1, 3 * 20 * 4, 10 ** 6):       # 1 x-row, 3 rows (uneven last slab), everything
        enc = open_encoder(b, slab_voxels=slab_voxels)
        chunks = list(enc.chunks(x, m))
        assert chunks[0][0] == 0 and chunks[-1][1] == b.grid.num_voxels
        assert all(a[1] == c[0] for a, c in zip(chunks, chunks[1:]))         # contiguous, in order
        h, g = enc.hidden(x, m)
        np.testing.assert_allclose(h, h_t[0].numpy(), rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(g, g_t[0].numpy(), rtol=1e-4, atol=1e-4)


def test_parity_report_within_tolerance(env):
    p = env["meta"]["parity"]["fp32"]
    assert p["ok"] and p["rel_err_feat"] <= 1e-3 and p["rel_err_feat_adapted"] <= 1e-3
    assert min(p["agreement_main"], p["agreement_adapted"], p["agreement_identifier"]) >= 0.999
    if SHARED_SAMPLE.exists():
        assert "ca9a282c9e77460f8360f564131a8af5" in p["frame"]       # checked on the real keyframe
    q = env["meta"]["variants"]["int8"]["parity"]
    assert q["rel_err_feat"] > p["rel_err_feat"]                      # int8 really is a different model
    assert all((env["bundle"] / f"{k}.int8.onnx").is_file() for k in ("planes", "voxels_0"))


def _torch_labels_on_random_frame(ckpt, bundle_dir, seed: int, grid_shape=None):
    """A random frame at 400x225 -> (Predictor of the bundle, its bank, images, rig, the torch model's reference
    labels read out on `grid_shape`)."""
    model, _ckpt, _cfg = load_model(ckpt)
    b = Bundle.load(bundle_dir)
    pred = Predictor(b)
    bank = b.load_bank()
    rng = np.random.default_rng(seed)
    rig = Rig([c.scaled(400, 225) for c in b.rig])
    images = {c.name: rng.integers(0, 255, (225, 400, 3), dtype=np.uint8) for c in rig}
    x, m = pred.prepare(images, rig)
    with torch.no_grad():
        out = model(torch.from_numpy(x), torch.from_numpy(m), grid_shape=grid_shape)
    want = reference_labels(out["feat"][0].numpy(), out["feat_adapted"][0].numpy(), bank, b.heads)
    return pred, bank, images, rig, want


def test_runtime_matches_torch_on_another_frame(env):
    """Independent of the exporter's own check: torch forward vs Predictor on a different frame."""
    pred, bank, images, rig, want = _torch_labels_on_random_frame(env["ckpt"], env["bundle"], 7)
    for ident, key in (("none", "main"), ("min-entropy", "identifier")):
        got = pred.predict(images, rig, bank, ident).semantics.reshape(-1)
        assert np.mean(got == want[key]) >= 0.999


def test_logsigmoid_softplus_equals_softplus():
    x = torch.linspace(-100, 100, 20001)
    assert torch.allclose(LogSigmoidSoftplus()(x), torch.nn.functional.softplus(x), atol=1e-6, rtol=1e-6)
    m = export_activations(torch.nn.Sequential(torch.nn.Linear(3, 3), torch.nn.Softplus()))
    assert isinstance(m[1], LogSigmoidSoftplus)


def test_failed_parity_writes_nothing(env):
    out = env["root"] / "never"
    with pytest.raises(AgoInputError, match="parity check failed"):
        export_bundle(env["ckpt"], out, bank_prompts=[], real_frame=False, tolerance=Tolerance(-1.0, 1.0),
                      log=lambda s: None)
    assert not out.exists()
    assert not [p for p in env["root"].iterdir() if p.name.startswith(".never")]


def test_failed_parity_keeps_existing_bundle(env, tmp_path):
    import shutil

    out = tmp_path / "b"
    shutil.copytree(env["bundle"], out)
    before = (out / "bundle.json").read_bytes()
    with pytest.raises(AgoInputError):
        export_bundle(env["ckpt"], out, bank_prompts=[], real_frame=False, tolerance=Tolerance(-1.0, 1.0),
                      log=lambda s: None)
    assert (out / "bundle.json").read_bytes() == before


def test_cli_export_synthetic_frame_and_bad_checkpoint(env, tmp_path):
    out = tmp_path / "synth_bundle"
    r = subprocess.run([sys.executable, "-m", "ago_runtime", "export", str(env["ckpt"]), "-o", str(out),
                        "--no-real-frame", "--train-bank-only", "--static-sampling"], capture_output=True, text=True,
                       cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    meta = json.loads((out / "bundle.json").read_text())
    assert meta["parity"]["fp32"]["frame"].startswith("synthetic") and meta["parity"]["fp32"]["ok"]
    assert set(meta["banks"]) == {"train"}
    # --static-sampling: every entry sampled, no data-dependent shape (the default bundle of env has NonZero)
    assert "NonZero" not in {n.op_type for n in onnx.load(str(out / "planes.onnx")).graph.node}
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    r = subprocess.run([sys.executable, "-m", "ago_runtime", "export", str(bad), "-o", str(tmp_path / "x")],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1].startswith(f"error: {bad}")
    assert not (tmp_path / "x").exists()


def test_export_on_a_finer_readout_grid(env, tmp_path):
    """`ago export --readout-grid`: the bundle predicts on the finer grid, reading the model's planes at its
    voxel centres exactly as AGOModel.forward(grid_shape=...) does (`ago eval --readout gt`)."""
    out = tmp_path / "fine"
    r = subprocess.run([sys.executable, "-m", "ago_runtime", "export", str(env["ckpt"]), "-o", str(out),
                        "--no-real-frame", "--train-bank-only", "--readout-grid", "40x40x8"],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    meta = json.loads((out / "bundle.json").read_text())
    assert meta["grid"]["shape"] == [40, 40, 8] and meta["model_grid"]["shape"] == [20, 20, 4]
    assert meta["parity"]["fp32"]["ok"] and meta["parity"]["fp32"]["num_voxels"] == 40 * 40 * 8
    card = json.loads((out / "card.json").read_text())
    assert card["readout"] == {"grid": [40, 40, 8], "model_grid": [20, 20, 4]}
    assert "read out at 40x40x8 (trained at 20x20x4)" in card["summary"]
    # scores of `ago eval --readout gt` are flagged on a card whose bundle stays on the model grid
    from ago_export.card import summary

    base = {"trained_on": {"kind": "synthetic"}, "val_scores": {"mIoU": 15.0, "readout": "gt"}}
    assert "not this bundle's" in summary({**base, "readout": {"grid": [20, 20, 4], "model_grid": [20, 20, 4]}})
    assert "not this bundle's" not in summary({**base, "readout": card["readout"]})
    pred, bank, images, rig, want = _torch_labels_on_random_frame(env["ckpt"], out, 3, grid_shape=(40, 40, 8))
    got = pred.predict(images, rig, bank, "none").semantics
    assert got.shape == (40, 40, 8)
    assert np.mean(got.reshape(-1) == want["main"]) >= 0.999
    # the default (no option) stays on the model's grid
    assert env["meta"]["grid"]["shape"] == [20, 20, 4] == env["meta"]["model_grid"]["shape"]
    for bad in ("40x40", "0x40x8", "fine"):
        r = subprocess.run([sys.executable, "-m", "ago_runtime", "export", str(env["ckpt"]), "-o",
                            str(tmp_path / "bad"), "--readout-grid", bad], capture_output=True, text=True, cwd=tmp_path)
        assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith("error: --readout-grid")
        assert not (tmp_path / "bad").exists()


# ---------------------------------------------------------------------------- the restructured graphs
def _tpv_model(k: int, offsets: int, seed: int = 0):
    """A tiny model whose TPV offsets and attention weights are far from their zero init, so samples
    land outside the maps (the canvas frames must reproduce zero padding) and weights are uneven."""
    from ago_train.model import ModelConfig

    cfg = ModelConfig.preset("tiny")
    cfg.cameras_per_query = cfg.cameras_per_query_side = k
    cfg.num_sampling_offsets = offsets
    torch.manual_seed(seed)
    model = cfg.build().eval()
    with torch.no_grad():
        for name, p in model.encoder.named_parameters():
            if "sampling_offsets" in name:
                p.normal_(0, 3.0)          # offsets of several pixels, many outside the maps
            elif "attention_weights" in name:
                p.normal_(0, 0.5)
    return cfg, model


@pytest.mark.parametrize("k,offsets", [(2, 1), (6, 2), (3, 2)])   # top-k atlas, dense, k=3 with 2 offsets
def test_export_tpv_equals_the_trained_encoder(k, offsets):
    """ExportTPV (one grid_sample per attention over zero-framed canvases, per-frame geometry) gives
    the trained TPVEncoder's planes."""
    from ago_export.graphs import ExportTPV
    from ago_runtime.geometry.camera import Rig
    from ago_runtime.geometry.preprocess import Preprocess

    cfg, model = _tpv_model(k, offsets)
    x = torch.randn(1, 6, 3, cfg.image_height, cfg.image_width)
    m = torch.from_numpy(Preprocess(cfg.image_width, cfg.image_height).ego2img(Rig.nuscenes_like(1600, 900))[None])
    with torch.no_grad():
        feats = model.fpn(model.backbone(x[0]))
        want = model.encoder(feats, m)
        got = ExportTPV(model.encoder)(feats, m[0])
    for p in ("xy", "xz", "yz"):
        rows, cols = model.encoder.plane_hw[p]
        ref = want[p][0].reshape(-1, rows * cols).t()            # (Q, D)
        assert torch.allclose(got[p], ref, atol=2e-5, rtol=1e-4), (p, float((got[p] - ref).abs().max()))


@pytest.mark.parametrize("k,offsets", [(2, 1), (6, 2)])
def test_compact_and_static_sampling_graphs_agree(tmp_path, k, offsets):
    """planes.onnx traced with compact sampling (the default: only the entries a camera sees, NonZero) and
    with --static-sampling (every entry, no data-dependent shapes) give the same planes in onnxruntime, on
    frames other than the trace's: a nuScenes rig, the same rig moved, and a rig that sees nothing."""
    ort = pytest.importorskip("onnxruntime")
    import warnings

    from ago_export.graphs import PlanesGraph
    from ago_runtime.geometry.preprocess import Preprocess

    cfg, model = _tpv_model(k, offsets)
    example = (torch.zeros(1, 6, 3, cfg.image_height, cfg.image_width), torch.eye(4).expand(1, 6, 4, 4).contiguous())
    sessions = {}
    for static in (False, True):
        path = tmp_path / f"planes_{static}.onnx"
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            torch.onnx.export(PlanesGraph(model, static_sampling=static).eval(), example, str(path), dynamo=False,
                              opset_version=17, input_names=["images", "ego2img"], do_constant_folding=True)
        assert ("NonZero" in {n.op_type for n in onnx.load(str(path)).graph.node}) == (not static)
        sessions[static] = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    m = torch.from_numpy(Preprocess(cfg.image_width, cfg.image_height).ego2img(Rig.nuscenes_like(1600, 900))[None])
    moved = m.clone()
    moved[..., :3, 3] += torch.tensor([3.0, -2.0, 0.5])
    x = torch.randn(1, 6, 3, cfg.image_height, cfg.image_width, generator=torch.Generator().manual_seed(5))
    seen = []
    for ego2img in (m, moved, torch.zeros(1, 6, 4, 4)):
        feed = {"images": x.numpy(), "ego2img": ego2img.numpy().astype(np.float32)}
        compact, static = sessions[False].run(None, feed), sessions[True].run(None, feed)
        with torch.no_grad():
            want = PlanesGraph(model)(x, ego2img)          # eager torch: the compact form, as training
            seen.append(int((model.encoder.canvas.frames["xz"](ego2img[0])["weight"] > 0).sum()))
        for a, b, w in zip(compact, static, want):
            assert np.abs(a - b).max() <= 1e-4 * max(1.0, float(np.abs(b).max()))
            if k == 6:   # k < 6: onnxruntime's TopK may break a tie between cameras unlike torch's (both graphs alike)
                assert np.abs(a - w.numpy()).max() <= 1e-4 * max(1.0, float(w.abs().max()))
    assert seen[0] > 0 and seen[2] == 0


def test_canvas_frames_keep_maps_apart():
    """Samples anywhere around a map in the canvas read exactly what grid_sample with zero padding
    reads from that map alone: nothing from the neighbouring maps."""
    import torch.nn.functional as F

    from ago_train.model.tpv_canvas import CanvasLayout, canvas_coords, plane_canvas

    torch.manual_seed(0)
    hw = {"xy": (5, 7), "xz": (5, 3), "yz": (7, 3)}
    layout = CanvasLayout.planes(hw)
    maps = [torch.rand(2, *hw[p]) + 1.0 for p in ("xy", "xz", "yz")]   # all > 1: any bleed shows
    canvas = plane_canvas(maps, layout)[None]
    for p, mp in zip(("xy", "xz", "yz"), maps):
        rows, cols = hw[p]
        px = torch.empty(1, 400).uniform_(-3, cols + 3)
        py = torch.empty(1, 400).uniform_(-3, rows + 3)
        want = F.grid_sample(mp[None], torch.stack([px / cols * 2 - 1, py / rows * 2 - 1], -1)[None],
                             align_corners=False)
        _, col0, _, _ = layout.blocks[p]
        grid = canvas_coords(px, py, -0.5, torch.tensor(cols + 0.5), -0.5, torch.tensor(rows + 0.5),
                             col0 + 1.0, 1.0, layout)
        got = F.grid_sample(canvas, grid[None], align_corners=False)
        assert torch.allclose(got, want, atol=1e-5)


@pytest.mark.parametrize("decoder_layers,adapter_depth", [(1, 1), (2, 3), (1, 4)])
def test_voxel_stages_equal_the_model_for_any_depth(decoder_layers, adapter_depth):
    """The staged per-voxel MLP (first linear in the planes, then one stage per layer: the decoder's toward h,
    the adapter's from h to g) gives the model's forward_hidden for any decoder / adapter depth."""
    from ago_export.graphs import PlanesGraph, VoxelsReference, voxel_stages
    from ago_runtime.geometry.camera import Rig
    from ago_runtime.predict.decision import Branch
    from ago_runtime.geometry.preprocess import Preprocess
    from ago_train.model import ModelConfig

    cfg = ModelConfig.preset("tiny")
    cfg.decoder_layers, cfg.adapter_depth = decoder_layers, adapter_depth
    torch.manual_seed(2)
    model = cfg.build().eval()
    stages = voxel_stages(model)
    assert [s.branch for s in stages] == [Branch.MAIN] * (decoder_layers - 1) + [Branch.ADAPTED] * max(1, adapter_depth - 1)
    x = torch.randn(1, 6, 3, cfg.image_height, cfg.image_width)
    m = torch.from_numpy(Preprocess(cfg.image_width, cfg.image_height).ego2img(Rig.nuscenes_like(1600, 900))[None])
    with torch.no_grad():
        h_t, g_t = model.forward_hidden(x, m)
        xy, xz, yz = PlanesGraph(model)(x, m)
        h, g = VoxelsReference(model)(xy, xz, yz)
    assert torch.allclose(h, h_t[0], atol=1e-5) and torch.allclose(g, g_t[0], atol=1e-5)


def test_deeper_model_exports_and_keeps_parity(tmp_path):
    """A 2-layer decoder and a 3-layer adapter: three voxel stages, runtime == torch."""
    from ago_train.model import ModelConfig

    cfg = ModelConfig.preset("tiny")
    cfg.pretrained, cfg.decoder_layers, cfg.adapter_depth = False, 2, 3
    ckpt = random_checkpoint(tmp_path / "deep.pt", cfg, prompts="cw", seed=4)
    meta = export_bundle(ckpt, tmp_path / "b", bank_prompts=[], real_frame=False, log=lambda s: None)
    assert [st["branch"] for st in meta["voxel_stages"]] == ["main", "adapted", "adapted"]
    p = meta["parity"]["fp32"]
    assert p["ok"] and min(p["agreement_main"], p["agreement_adapted"], p["agreement_identifier"]) >= 0.999


@pytest.mark.parametrize("bias", [-2.0, 2.0])
def test_free_bias_is_exported_and_applied(tmp_path, bias):
    """A model with a learnt free bias (ModelConfig.free_bias): the bundle carries it, the runtime adds it to
    the free score, and its labels equal torch's (class_logits with the bias) on a random frame."""
    from ago_train.checkpoint import CheckpointContract
    from ago_train.model import ModelConfig
    from ago_train.model.text_logits import class_logits

    cfg = ModelConfig.preset("tiny")
    cfg.pretrained, cfg.free_bias = False, True
    ckpt = random_checkpoint(tmp_path / "fb.pt", cfg, prompts="cw", seed=5)
    state = CheckpointContract.load(ckpt)
    state.model["free_bias"] = torch.tensor(bias)
    state.save(ckpt)
    export_bundle(ckpt, tmp_path / "b", bank_prompts=[], real_frame=False, log=lambda s: None)
    b = Bundle.load(tmp_path / "b")
    assert b.heads.free_bias == pytest.approx(bias)
    pred, bank, images, rig, want = _torch_labels_on_random_frame(ckpt, tmp_path / "b", 3)
    got = pred.predict(images, rig, bank, "none").semantics.reshape(-1)
    assert np.mean(got == want["main"]) >= 0.999
    model, _c, _cfg = load_model(ckpt)
    x, m = pred.prepare(images, rig)
    with torch.no_grad():
        out = model(torch.from_numpy(x), torch.from_numpy(m))
        torch_labels = class_logits(out["feat"], torch.from_numpy(bank.embeddings), torch.from_numpy(bank.phrase_class),
                                    bank.num_classes, out["free_embedding"], free_bias=out["free_bias"])[0].argmax(-1)
    assert np.mean(torch_labels.numpy() == got) >= 0.999
    free_share = np.mean(got == bank.num_classes)
    assert free_share > 0.9 if bias > 0 else free_share < 0.1     # the bias really moves the decision
