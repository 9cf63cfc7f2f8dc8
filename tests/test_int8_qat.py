"""int8 that keeps the labels: the `quant` training switch (ago_train/quant.py: fake int8, distillation from the
fp32 model) and `ago export --int8` (static QDQ planes calibrated on training frames, ago_export/quantize.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from ago_runtime.errors import AgoInputError  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_int8_qat")  # one worker builds the module fixtures (--dist loadgroup)

REPO = Path(__file__).resolve().parents[1]
GRID = "20x20x4"


def _ago(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, AGO_NO_PROGRESS="1", OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "ago_runtime.cli", *args], cwd=REPO, env=env,
                          capture_output=True, text=True)


@pytest.fixture(scope="module")
def town(tmp_path_factory) -> dict:
    """A 2-frame synthetic town on the tiny model's grid with cw pseudo-labels, and a 2-step tiny fp32 run on it."""
    root = tmp_path_factory.mktemp("int8_qat")
    os.environ["AGO_CACHE_DIR"] = str(root / "cache")
    data, pseudo, run = root / "synth", root / "pseudo", root / "fp32"
    for args in (("synth", "--out", str(data), "--scenes", "1", "--frames", "2", "--image-size", "192x128", "--grid",
                  GRID, "--seed", "5", "--val-fraction", "0"),
                 ("pseudo-labels", "--data", str(data), "--out", str(pseudo), "--prompts", "cw", "--grid", GRID,
                  "--split", "all", "--embedder", "sim", "--keyframes", "2"),
                 ("train", "--config", "tiny", "--data", str(data), "--pseudo", str(pseudo), "--out", str(run),
                  "--set", "train_split=all", "--set", "device=cpu")):
        r = _ago(*args)
        assert r.returncode == 0, r.stderr
    return {"root": root, "data": data, "pseudo": pseudo, "fp32": run / "last.pt"}


def test_quant_config_field_is_checked():
    from ago_train.train_config import TrainConfig

    tiny = TrainConfig.preset("tiny")
    assert tiny.quant == "none"
    with pytest.raises(AgoInputError, match="quant must be one of"):
        tiny.with_overrides(["quant=int4"])
    with pytest.raises(AgoInputError, match="init_from"):
        tiny.with_overrides(["quant=int8"])
    cfg = tiny.with_overrides(["quant=int8", "init_from=x.pt", "feature_cache=auto"])
    assert cfg.quant == "int8" and not cfg.uses_feature_cache()   # fake int8 changes the frozen stages' maps


def test_fake_quant_weights_per_channel_and_activation_ranges():
    from ago_train.quant import ActivationFakeQuant, WeightFakeQuant

    w = torch.randn(4, 3, 3, 3) * torch.tensor([0.01, 1.0, 10.0, 100.0]).view(4, 1, 1, 1)
    q = WeightFakeQuant()(w)
    for c in range(4):   # each output channel on its own grid of <= 255 levels, max |w| kept exactly
        scale = w[c].abs().max() / 127
        levels = (q[c] / scale).round()
        assert torch.allclose(q[c], levels * scale, atol=1e-6 * float(scale) * 127)
        assert levels.abs().max() == 127 and torch.unique(levels).numel() <= 255
        assert (q[c] - w[c]).abs().max() <= scale / 2 + 1e-6
    act = ActivationFakeQuant().train()
    x = torch.linspace(-1, 5, 1000, requires_grad=True)
    y = act(x)
    assert float(act.lo) == -1 and float(act.hi) == 5 and torch.unique(y.detach()).numel() <= 256
    y.sum().backward()
    assert torch.equal(x.grad, torch.ones_like(x))     # straight through inside the range
    act(torch.full((10,), 100.0))                      # training: the range moves (moving average) ...
    hi = float(act.hi)
    assert 5 < hi < 100
    act.eval()
    step = (hi - float(act.lo)) / 255
    assert abs(float(act(torch.full((3,), 1e4)).max()) - hi) <= step   # ... eval: fixed, clipped to it


def test_fake_quant_model_keeps_plain_weight_names():
    from ago_train.model import ModelConfig
    from ago_train.quant import attach_fake_quant, load_model_state, model_state

    cfg = ModelConfig.preset("tiny")
    cfg.pretrained = False
    torch.manual_seed(0)
    plain = cfg.build()
    quant = cfg.build()
    quant.load_state_dict(plain.state_dict())
    n = attach_fake_quant(quant)
    convs = {name for name, m in plain.named_modules() if isinstance(m, torch.nn.Conv2d)}
    fpn_out = {name for name in convs if name.startswith("fpn.output.")}
    assert fpn_out and n == len(convs) - len(fpn_out) > 0   # the FPN outputs stay float, as the export keeps them
    assert not any(hasattr(m, "input_quant") for name, m in quant.named_modules() if name in fpn_out)
    assert set(model_state(quant)) == set(plain.state_dict())      # checkpoints keep the plain names
    plain.eval(), quant.eval()
    images, ego2img = torch.randn(1, 6, 3, 64, 96), torch.eye(4).expand(1, 6, 4, 4).clone()
    ego2img[..., 0, 3] = 48.0
    ego2img[..., 1, 3] = 32.0
    with torch.no_grad():
        a = plain(images, ego2img)["feat"]
        b = quant(images, ego2img)["feat"]
    assert not torch.equal(a, b) and float((a - b).norm() / a.norm()) < 0.2   # int8 noise, not another model
    load_model_state(quant, {k: v * 0 for k, v in plain.state_dict().items()})   # loads back under plain names
    assert all(float(v.abs().max()) == 0 for k, v in model_state(quant).items() if k.endswith(".weight"))


def test_short_qat_run_then_int8_export(town, tmp_path):
    """`ago train --set quant=int8 --set init_from=FP32` runs (distillation losses logged, the teacher's
    calibration kept, a plain checkpoint), and `ago export --int8` of it calibrates on its training frames."""
    qat = tmp_path / "qat"
    r = _ago("train", "--config", "tiny", "--data", str(town["data"]), "--pseudo", str(town["pseudo"]),
             "--out", str(qat), "--set", "train_split=all", "--set", "device=cpu", "--set", "quant=int8",
             "--set", f"init_from={town['fp32']}", "--set", "lr=1e-4", "--set", "log_every=1")
    assert r.returncode == 0, r.stderr
    logs = [json.loads(ln) for ln in (qat / "log.jsonl").read_text().splitlines()]
    assert logs and all(np.isfinite(rec["distill_main"]) and rec["distill_main"] >= 0 for rec in logs)
    assert all(0.5 <= rec["agree_main"] <= 1 for rec in logs)          # a student close to its teacher
    ckpt = torch.load(qat / "last.pt", weights_only=True)
    fp32 = torch.load(town["fp32"], weights_only=True)
    assert ckpt["train_config"]["quant"] == "int8" and set(ckpt["model"]) == set(fp32["model"])
    assert ckpt["calibration"]["scale_main"] == fp32["calibration"]["scale_main"]
    bundle = tmp_path / "bundle"
    r = _ago("export", str(qat / "last.pt"), "-o", str(bundle), "--int8", "--no-real-frame", "--train-bank-only")
    assert r.returncode == 0, r.stderr
    assert f"2 frames of split 'all' of {town['data']}" in r.stderr       # the run's own training frames
    meta = json.loads((bundle / "bundle.json").read_text())
    int8 = meta["variants"]["int8"]
    assert int8["parity"]["ok"] and int8["method"] == "static-qdq; sampled-feature convolutions float32"
    assert set(int8["graphs"].values()) <= set(meta["files"])


def test_int8_export_is_qdq_and_agrees_with_fp32(town, tmp_path):
    """A random tiny checkpoint (no training data recorded): --int8 needs --calibration-data; the planes graph is
    a QDQ graph with int8 per-channel convolution weights that onnxruntime runs, its labels close to fp32's."""
    import onnx

    from ago_export.export import export_bundle
    from ago_export.testing import random_checkpoint
    from ago_runtime.formats.nuscenes import NuScenesDataset
    from ago_runtime.predict.predictor import Predictor

    ckpt = random_checkpoint(tmp_path / "tiny.pt", "tiny", prompts="cw", seed=1)
    with pytest.raises(AgoInputError, match="--calibration-data"):
        export_bundle(ckpt, tmp_path / "refused", int8=True, real_frame=False, bank_prompts=[], log=lambda s: None)
    assert not (tmp_path / "refused").exists()
    r = _ago("export", str(ckpt), "-o", str(tmp_path / "b0"), "--calibration-data", str(town["data"]))
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith("error: --calibration-data:")
    bundle = tmp_path / "bundle"
    export_bundle(ckpt, bundle, int8=True, real_frame=False, bank_prompts=[], log=lambda s: None,
                  calibration_data=town["data"])
    graph = onnx.load(str(bundle / "planes.int8.onnx")).graph
    ops = [n.op_type for n in graph.node]
    assert ops.count("QuantizeLinear") > 0 and ops.count("DequantizeLinear") > ops.count("QuantizeLinear")
    weights = {i.name: i for i in graph.initializer}
    qweights = [weights[n.input[0]] for n in graph.node if n.op_type == "DequantizeLinear" and n.input[0] in weights
                and weights[n.input[0]].data_type == onnx.TensorProto.INT8 and len(weights[n.input[0]].dims) == 4]
    assert qweights and all(any(a.name == "axis" for a in n.attribute) for n in graph.node
                            if n.op_type == "DequantizeLinear" and n.input[0] in {w.name for w in qweights})
    fp32, int8 = Predictor(bundle), Predictor(bundle, int8=True)
    bank = fp32.bundle.load_bank()
    f = NuScenesDataset(town["data"], load_extras=False)[0]
    x, m = fp32.prepare(f.images, f.rig)
    a = fp32.predict_arrays(x, m, bank).semantics
    b = int8.predict_arrays(x, m, bank).semantics
    assert (a == b).mean() >= 0.9


def test_int8_float_keeps_the_named_modules_convolutions_in_float32(town, tmp_path):
    """`ago export --int8 --int8-float backbone.convs.0`: exactly the convolutions of that torch module stay
    float32 Conv nodes in planes.int8.onnx (their weights float, no DequantizeLinear in front), besides those that
    always do (the FPN outputs and the TPV encoder's value projections, which make the sampled features: the
    modules of QAT's FLOAT_IN_INT8), every other backbone / FPN convolution is int8, and the variant's method
    records the modules. A name that is no module with
    a convolution is refused before any export work, one naming only the TPV encoder's functional convolutions
    when the graph is quantised; --int8-float without --int8 is refused."""
    import onnx

    from ago_export.export import export_bundle
    from ago_export.quantize import in_modules, node_module
    from ago_export.export import load_model

    from ago_train.quant import FLOAT_IN_INT8

    keep = ("backbone.convs.0",)
    bundle = tmp_path / "mixed"
    export_bundle(town["fp32"], bundle, int8=True, real_frame=False, bank_prompts=[], log=lambda s: None,
                  int8_float=keep)
    graph = onnx.load(str(bundle / "planes.int8.onnx")).graph
    weights = {i.name: i for i in graph.initializer}
    produced = {o: n for n in graph.node for o in n.output}
    float_convs, int8_convs = [], []
    for n in graph.node:
        if n.op_type != "Conv":
            continue
        w = n.input[1]
        src = produced.get(w)
        (int8_convs if src is not None and src.op_type == "DequantizeLinear" else float_convs).append(n.name)
        if w in weights:
            assert weights[w].data_type == onnx.TensorProto.FLOAT
    names = {n for n, _ in load_model(town["fp32"])[0].named_modules()}
    modules = sorted({node_module(c, names) for c in float_convs if not c.startswith("/tpv/")})
    assert modules == ["backbone.convs.0.0", "fpn.output.0", "fpn.output.1", "fpn.output.2"], modules
    # QAT leaves float exactly the modules the export keeps float on its own (the sampled features' rule)
    assert [m for m in modules if in_modules(m, FLOAT_IN_INT8)] == ["fpn.output.0", "fpn.output.1", "fpn.output.2"]
    assert [c for c in float_convs if c.startswith("/tpv/")] and not [c for c in int8_convs if c.startswith("/tpv/")]
    assert any(node_module(c, names).startswith("backbone.convs.1") for c in int8_convs)
    meta = json.loads((bundle / "bundle.json").read_text())
    assert meta["variants"]["int8"]["method"] == ("static-qdq; sampled-feature convolutions float32; "
                                                  "float32: backbone.convs.0")

    for name, message in (("backbone.nope", "no module of the model"), ("encoder.layers.0.image_value", "/tpv/Conv")):
        with pytest.raises(AgoInputError, match=message):
            export_bundle(town["fp32"], tmp_path / "refused", int8=True, real_frame=False, bank_prompts=[],
                          log=lambda s: None, int8_float=(name,))
        assert not (tmp_path / "refused").exists()
    r = _ago("export", str(town["fp32"]), "-o", str(tmp_path / "b1"), "--int8-float", "backbone.convs.0")
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith("error: --int8-float:")


def test_infer_stages_benchmark_times_every_stage_and_bounds_the_ratio(town, tmp_path):
    """benchmarks/infer_stages.py on an int8 export: a row per stage for each variant, the whole frame's ratio, label
    agreement, the planes time a 1.3x target would need and the fp32 planes graph's onnxruntime profile; bad options
    are one `error:` line, exit 2, no file."""
    from ago_export.export import export_bundle
    from ago_export.testing import random_checkpoint

    ckpt = random_checkpoint(tmp_path / "tiny.pt", "tiny", prompts="cw", seed=1)
    bundle = tmp_path / "bundle"
    export_bundle(ckpt, bundle, int8=True, real_frame=False, bank_prompts=[], log=lambda s: None,
                  calibration_data=town["data"])
    env = dict(os.environ, AGO_NO_PROGRESS="1", OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))

    def stages(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "benchmarks.infer_stages", "--bundle", str(bundle), *args],
                              cwd=REPO, env=env, capture_output=True, text=True)

    out = tmp_path / "stages.md"
    r = stages("--dataset", str(town["data"]), "--frames", "2", "--picture", "bev", "--variants", "fp32,int8-cpu",
               "--onnxruntime-ops", "--out", str(out))
    assert r.returncode == 0, r.stderr
    text = out.read_text()
    # the fp32 planes graph's onnxruntime profile: a row per operator type, the convolutions and sampling among them
    ort_rows = {ln.split("|")[1].strip(): float(ln.split("|")[2]) for ln in text.split("by operator type")[1].splitlines()
                if ln.startswith("| ") and ln.count("|") == 3 and not ln.startswith("| operator")}
    assert {"Conv", "GridSample"} <= set(ort_rows) and all(ms >= 0 for ms in ort_rows.values()) and ort_rows["Conv"] > 0
    for row in ("decode", "preprocess", "planes", "per-voxel", "heads", "picture", "npz", "**shared**",
                "**whole frame**"):
        line = next(ln for ln in text.splitlines() if ln.startswith(f"| {row}"))
        assert all(float(c.strip(" *")) >= 0 for c in line.split("|")[2:4])
    assert "| stage | fp32 | int8-cpu |" in text and "2 frames" in text
    assert "- int8-cpu: whole frame on one core" in text and "% of all voxels" in text and "planes graph would need" in text
    try:
        import openvino  # noqa: F401
    except ImportError:
        openvino = None
    if openvino is not None:   # the per-operator profile of the int8 planes graph on OpenVINO
        r = stages("--dataset", str(town["data"]), "--frames", "1", "--picture", "none", "--variants", "fp32,fp32-openvino",
                   "--openvino-ops", "--out", str(out))
        assert r.returncode == 0, r.stderr
        assert "| stage | fp32 | fp32-openvino |" in out.read_text() and "- fp32-openvino: whole frame" in out.read_text()
        rows = [ln for ln in out.read_text().split("## Run")[1].splitlines() if ln.startswith("| ") and "_" in ln
                and ln.count("|") == 4 and not ln.startswith("| operator")]
        assert rows and all(float(ln.split("|")[3]) >= 0 for ln in rows)
    for bad, what in ((("--dataset", str(town["data"]), "--variants", "int8-cpu"), "--variants"),
                      (("--dataset", str(tmp_path / "missing")), "--dataset"),
                      (("--dataset", str(town["data"]), "--frames", "0"), "--frames"),
                      (("--dataset", str(town["data"]), "--variants", "fp32,int8-cpu", "--out", str(tmp_path / "stages.md" / "x.md")),
                       str(tmp_path / "stages.md" / "x.md"))):
        r = stages(*bad, *(() if "--out" in bad else ("--out", str(tmp_path / "bad.md"))))
        assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith(f"error: {what}:"), r.stderr
        assert not (tmp_path / "bad.md").exists()
