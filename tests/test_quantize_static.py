"""Static QDQ int8 of the convolutions (ago_export.quantize.quantize_planes_static) and its calibration frames
(ago_export.calibration_frames): on a tiny ONNX graph of convolutions with a GridSample, and on real frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from ago_export.calibration_frames import MAX_CALIBRATION_FRAMES, planes_feeds, read_frames, spread  # noqa: E402
from ago_export.quantize import quantize_planes_static, sampled_feature_convs  # noqa: E402
from ago_runtime.errors import AgoInputError  # noqa: E402

from conftest import shared_path  # noqa: E402


def tiny_graph(path: Path) -> Path:
    """x (1,3,16,16) -> Conv 3x3 (8) -> Clip [0, 6] (ReLU6) -> Conv 1x1 (8) -> Conv 3x3 (8, "the FPN output") ->
    Pad (data movement) -> Conv 1x1 (8, "the value projection") -> GridSample(grid) -> y (1,8,8,8).

    The first convolution's weights are large (as a batch norm folded into them makes them), so its
    pre-activation spans far more than the [0, 6] its ReLU6 keeps. The last two convolutions make the sampled
    features: they stay float32 (sampled_feature_convs)."""
    rng = np.random.default_rng(0)
    w1 = (rng.normal(size=(8, 3, 3, 3)) * 4).astype(np.float32)
    w2 = (rng.normal(size=(8, 8, 1, 1)) * 0.3).astype(np.float32)
    w3 = (rng.normal(size=(8, 8, 3, 3)) * 0.1).astype(np.float32)
    w4 = (rng.normal(size=(8, 8, 1, 1)) * 0.3).astype(np.float32)
    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["c1"], name="conv1", pads=[1, 1, 1, 1]),
        helper.make_node("Clip", ["c1", "lo", "hi"], ["r1"], name="relu6"),
        helper.make_node("Conv", ["r1", "w2", "b2"], ["c2"], name="conv2"),
        helper.make_node("Conv", ["c2", "w3", "b2"], ["c3"], name="fpn_output", pads=[1, 1, 1, 1]),
        helper.make_node("Pad", ["c3", "pads"], ["p3"], name="pad"),
        helper.make_node("Conv", ["p3", "w4", "b2"], ["c4"], name="value_projection"),
        helper.make_node("GridSample", ["c4", "grid"], ["y"], name="sample", align_corners=0),
    ]
    inits = [numpy_helper.from_array(w1, "w1"), numpy_helper.from_array(np.zeros(8, np.float32), "b1"),
             numpy_helper.from_array(w2, "w2"), numpy_helper.from_array(np.full(8, 0.1, np.float32), "b2"),
             numpy_helper.from_array(w3, "w3"), numpy_helper.from_array(w4, "w4"),
             numpy_helper.from_array(np.array([0, 0, 1, 1, 0, 0, 1, 1], np.int64), "pads"),
             numpy_helper.from_array(np.array(0, np.float32), "lo"),
             numpy_helper.from_array(np.array(6, np.float32), "hi")]
    graph = helper.make_graph(nodes, "tiny", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 16, 16]),
                                              helper.make_tensor_value_info("grid", TensorProto.FLOAT, [1, 8, 8, 2])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 8, 8, 8])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def feed(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"x": rng.normal(size=(1, 3, 16, 16)).astype(np.float32),
            "grid": rng.uniform(-1, 1, size=(1, 8, 8, 2)).astype(np.float32)}


@pytest.fixture(scope="module")
def quantised(tmp_path_factory):
    d = tmp_path_factory.mktemp("qdq")
    fp32 = tiny_graph(d / "tiny.onnx")
    out = quantize_planes_static(fp32, d / "tiny.qdq.onnx", [feed(s) for s in range(8)])
    return fp32, out


def producers(model) -> dict[str, object]:
    return {o: n for n in model.graph.node for o in n.output}


def test_convolutions_sit_between_quantize_and_dequantize(quantised):
    _, out = quantised
    model = onnx.load(str(out))
    made_by = producers(model)
    convs = [n for n in model.graph.node if n.op_type == "Conv" and n.name.startswith(("conv1", "conv2"))]
    assert len(convs) == 2
    for conv in convs:
        # activation and weight come from DequantizeLinear; the output goes through QuantizeLinear
        assert made_by[conv.input[0]].op_type == "DequantizeLinear"
        assert made_by[conv.input[1]].op_type == "DequantizeLinear"
        users = [n for n in model.graph.node if conv.output[0] in n.input]
        assert [u.op_type for u in users] == ["QuantizeLinear"]
    # per-channel weights: one scale per output channel
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    for conv in convs:
        w_dq = made_by[conv.input[1]]
        assert inits[w_dq.input[1]].shape == (8,)
        assert inits[w_dq.input[0]].dtype == np.int8


def test_the_convolutions_that_make_the_sampled_features_stay_float(quantised):
    """The value projection (its output goes straight to the GridSample) and the FPN output (its output reaches the
    value projection through a Pad only) keep float32 weights and write float32: no QuantizeLinear after them."""
    fp32, out = quantised
    assert sampled_feature_convs(onnx.load(str(fp32)).graph) == ["fpn_output", "value_projection"]
    model = onnx.load(str(out))
    made_by = producers(model)
    weights = {i.name for i in model.graph.initializer}
    for name in ("fpn_output", "value_projection"):
        (conv,) = [n for n in model.graph.node if n.op_type == "Conv" and n.name == name]
        assert conv.input[1] in weights   # the float weights themselves, no DequantizeLinear
        assert not [n for n in model.graph.node if conv.output[0] in n.input and n.op_type == "QuantizeLinear"]
    gs = next(n for n in model.graph.node if n.op_type == "GridSample")
    assert made_by[gs.input[0]].name == "value_projection"


def test_relu6_is_folded_into_the_convolution_output_range(quantised):
    """The Clip goes (QDQ removes it) and the first conv's output is quantised over [0, 6], not over its far
    wider pre-activation range: uint8 scale 6/255, zero point 0."""
    _, out = quantised
    model = onnx.load(str(out))
    assert not [n for n in model.graph.node if n.op_type == "Clip"]
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    conv1 = next(n for n in model.graph.node if n.name.startswith("conv1"))
    q = next(n for n in model.graph.node if n.op_type == "QuantizeLinear" and n.input[0] == conv1.output[0])
    assert float(inits[q.input[1]]) == pytest.approx(6 / 255, rel=1e-3)
    assert int(inits[q.input[2]]) == 0 and inits[q.input[2]].dtype == np.uint8


def test_grid_sample_stays_float(quantised):
    _, out = quantised
    model = onnx.load(str(out))
    made_by = producers(model)
    gs = [n for n in model.graph.node if n.op_type == "GridSample"]
    assert len(gs) == 1
    # its data input is the float value projection's output, its grid is the float graph input, and its
    # output is the graph's float output with no QuantizeLinear after it
    assert made_by[gs[0].input[0]].op_type == "Conv"
    assert gs[0].input[1] == "grid"
    assert gs[0].output[0] == "y"
    assert not [n for n in model.graph.node if "y" in n.input]
    assert model.graph.output[0].type.tensor_type.elem_type == TensorProto.FLOAT


def test_results_close_to_fp32(quantised):
    fp32, out = quantised
    a = ort.InferenceSession(str(fp32), providers=["CPUExecutionProvider"])
    b = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    for seed in (100, 101):   # frames the calibration never saw
        (ref,), (got,) = a.run(None, feed(seed)), b.run(None, feed(seed))
        rel_rms = np.sqrt(np.mean((got - ref) ** 2) / np.mean(ref ** 2))
        assert 0 < rel_rms < 0.05


def test_bad_calibration_feeds_are_one_line_errors_and_write_nothing(tmp_path):
    fp32 = tiny_graph(tmp_path / "tiny.onnx")
    out = tmp_path / "tiny.qdq.onnx"
    bad_shape = feed(0)
    bad_shape["x"] = bad_shape["x"][:, :2]
    nan = feed(0)
    nan["x"][0, 0, 0, 0] = np.nan
    cases = {
        "no calibration frames": [],
        "gives inputs ['x']": [{"x": feed(0)["x"]}],
        "the graph takes float32 (1, 3, 16, 16)": [bad_shape],
        "holds NaN or inf": [nan],
    }
    for problem, feeds in cases.items():
        with pytest.raises(AgoInputError) as e:
            quantize_planes_static(fp32, out, feeds)
        msg = str(e.value)
        assert msg.startswith("--calibration-data: ") and problem in msg and "\n" not in msg
    with pytest.raises(AgoInputError, match="calibration method: 'entropy'; expected one of"):
        quantize_planes_static(fp32, out, [feed(0)], method="entropy")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny.onnx"]   # no output, no temp file left


def test_spread_bounds_and_covers():
    assert spread(3, 5) == [0, 1, 2]
    picked = spread(41, 4)
    assert picked == sorted(set(picked)) and len(picked) == 4 and picked[0] == 0 and picked[-1] == 40


def test_read_frames_refuses_bad_folders(tmp_path):
    for folder, count, problem in [(tmp_path / "missing", 4, "folder not found"),
                                   (tmp_path, 0, f"must be 1..{MAX_CALIBRATION_FRAMES}"),
                                   (tmp_path, MAX_CALIBRATION_FRAMES + 1, f"must be 1..{MAX_CALIBRATION_FRAMES}"),
                                   (tmp_path, 4, "")]:   # an empty folder: no images
        with pytest.raises(AgoInputError) as e:
            read_frames(folder, count)
        assert str(e.value).startswith("--calibration-data: ") and problem in str(e.value)
    with pytest.raises(AgoInputError, match="--calibration-data: no calibration frames"):
        planes_feeds([], None)


def test_calibration_frames_from_a_real_nuscenes_scene():
    from ago_runtime.geometry.preprocess import Preprocess

    root = shared_path("nuscenes-scene")
    frames = read_frames(root, 3, split="train")
    assert len(frames) == 3 and len({name for _, _, name in frames}) == 3   # three different keyframes
    with pytest.raises(AgoInputError, match="--calibration-data: .*no split 'nope'"):
        read_frames(root, 3, split="nope")
    feeds = planes_feeds(frames, Preprocess(width=64, height=32))
    assert feeds[0]["images"].shape == (1, 6, 3, 32, 64) and feeds[0]["images"].dtype == np.float32
    assert feeds[0]["ego2img"].shape == (1, 6, 4, 4)
    assert not np.allclose(feeds[0]["images"], feeds[-1]["images"])


def test_uncalibrated_range_sets_every_activation_range_without_frames(tmp_path):
    """Benchmarks of random-weight graphs: no calibration run, the fixed range everywhere, a Clip's [0, 6]."""
    fp32 = tiny_graph(tmp_path / "tiny.onnx")
    out = quantize_planes_static(fp32, tmp_path / "fixed.onnx", [], uncalibrated_range=(-8.0, 8.0))
    model = onnx.load(str(out))
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    scales = {n.input[0]: float(inits[n.input[1]]) for n in model.graph.node if n.op_type == "QuantizeLinear"}
    conv1, conv2 = (next(n for n in model.graph.node if n.name.startswith(c)) for c in ("conv1", "conv2"))
    assert scales["x"] == pytest.approx(16 / 255, rel=1e-3)
    assert scales[conv1.output[0]] == pytest.approx(6 / 255, rel=1e-3)
    assert scales[conv2.output[0]] == pytest.approx(16 / 255, rel=1e-3)
