"""int8 quantisation of an exported encoder: dynamic (MatMul/Gemm) or static QDQ (the convolutions).

- `quantize_encoder` (dynamic, onnxruntime.quantization.quantize_dynamic): takes an fp32 ONNX file; writes
  one whose MatMul/Gemm weights are int8 (activations are quantised on the fly per batch). Convolutions and
  GridSample stay float32. Used for the voxel stages (one Gemm each).
- `quantize_planes_static` (static, onnxruntime.quantization.quantize_static): takes planes.onnx and
  calibration feeds (real preprocessed frames, ago_export.calibration_frames); writes a QDQ graph whose
  convolutions (the image backbone and the FPN) run on int8 activations and int8 per-channel weights. The
  activation ranges are the min/max seen on the calibration frames (or their percentiles). GridSample, the
  attention MatMuls/Gemms and everything else stay float32, and so do the convolutions that make the features
  the TPV encoder samples (`sampled_feature_convs`: the value projections and the FPN outputs they read).
  In int8 those convolutions run faster, but what their int8 outputs need on the way to the samplers costs
  more than that: a dequantisation per sampler reading the value projection, and, behind the FPN outputs, a
  transpose that moves the channels of onnxruntime's int8 channels-last layout to the front (measured in
  benchmarks/results/paper_scale.md).
- `quantize_int8_graphs`: the bundle's int8 variant, what `ago export --int8` writes: planes.onnx static QDQ
  (calibrated on frames of the checkpoint's training split only) and every voxel stage dynamic. The same
  recipe serves a model fine-tuned with fake int8 first (`ago train --set quant=int8`, ago_train/quant.py);
  how many labels each keeps: benchmarks/results/int8_qat.md.

Settings (onnxruntime's guidance for x86 CPUs, in quantize_static's docstring): QDQ format; activations
uint8 (asymmetric), weights int8 (symmetric), per channel; reduce_range off (full 8-bit weights, right on
CPUs with VNNI: AVX512-VNNI or AVX-VNNI; CPUs without VNNI may saturate their int16 sums and lose accuracy).
"Clip" is quantised with "Conv": the backbone's ReLU6 after a convolution is then folded into that
convolution's output range ([0, 6] instead of the pre-activation's range, far wider in EfficientNet-Lite
with its batch norms folded into the weights). The graph is shape-inferred and optimised first
(`quant_pre_process`).
"""

from __future__ import annotations

import logging
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ago_runtime.atomic import atomic_path
from ago_runtime.errors import AgoInputError

STATIC_OP_TYPES = ["Conv", "Clip"]   # Clip: see the module doc (ReLU6 folded into the conv's output range)
# how the bundle's int8 variant names this rule in its method (bundle.json variants.int8.method; bundles made
# before it run every convolution in int8 and say "static-qdq" alone)
SAMPLED_FEATURES_FLOAT = "sampled-feature convolutions float32"
# ops that only move or reshape data: a convolution whose output reaches a sampler through these alone makes
# the sampled features (sampled_feature_convs)
DATA_MOVEMENT_OPS = frozenset({"Concat", "Pad", "Transpose", "Reshape", "Slice", "Split", "Squeeze", "Unsqueeze",
                               "Identity", "Flatten"})


@contextmanager
def _quiet_root_logger():
    """onnxruntime.quantization logs hints (e.g. about pre-processing) on the root logger."""
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)
    try:
        yield
    finally:
        root.setLevel(level)


def quantize_encoder(fp32_path: str | Path, int8_path: str | Path) -> Path:
    """Dynamic int8 of the MatMul/Gemm weights (see the module doc)."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    with _quiet_root_logger():
        quantize_dynamic(str(fp32_path), str(int8_path), weight_type=QuantType.QInt8,
                         op_types_to_quantize=["MatMul", "Gemm"])
    return Path(int8_path)


def check_feeds(fp32_path: str | Path, feeds: list[dict[str, np.ndarray]]) -> None:
    """Each feed must give every graph input, float32, of the graph's static shape: else one AgoInputError
    naming --calibration-data."""
    import onnx

    if not feeds:
        raise AgoInputError("--calibration-data", "no calibration frames")
    graph = onnx.load(str(fp32_path), load_external_data=False).graph
    want = {i.name: tuple(d.dim_value if d.HasField("dim_value") else None for d in i.type.tensor_type.shape.dim)
            for i in graph.input}
    for k, feed in enumerate(feeds):
        if set(feed) != set(want):
            raise AgoInputError("--calibration-data", f"frame {k} gives inputs {sorted(feed)}; the graph takes "
                                f"{sorted(want)}")
        for name, shape in want.items():
            a = np.asarray(feed[name])
            fits = a.ndim == len(shape) and all(s is None or s == n for s, n in zip(shape, a.shape))
            if a.dtype != np.float32 or not fits:
                raise AgoInputError("--calibration-data", f"frame {k}: {name} is {a.dtype} {a.shape}; the graph "
                                    f"takes float32 {shape}")
            if not np.isfinite(a).all():
                raise AgoInputError("--calibration-data", f"frame {k}: {name} holds NaN or inf")


def quantize_planes_static(fp32_path: str | Path, out_path: str | Path, feeds: list[dict[str, np.ndarray]],
                           keep_float: list[str] | None = None,
                           uncalibrated_range: tuple[float, float] | None = None, method: str = "minmax") -> Path:
    """Static QDQ int8 of planes.onnx's convolutions, calibrated on `feeds` (see the module doc).

    keep_float: node names left in float32 (e.g. a sensitive convolution), besides `sampled_feature_convs`,
    which always are. The file appears at out_path only when quantisation finished (temp name + rename).
    method: "minmax" (each activation's range: the min and max over the frames) or "percentile" (the 0.001 and
    99.999 percentiles; keeps every activation of every frame in memory while calibrating: few frames only).
    uncalibrated_range (benchmarks of random-weight graphs only, where the ranges do not matter): no
    calibration run, `feeds` unused; every quantised activation gets this range, a Clip's output [0, 6].
    onnxruntime's calibrator runs the graph with its optimisations off, which at the paper's scale needs more
    memory than the optimised graph (benchmarks/results/int8_static_paper.md)."""
    from onnxruntime.quantization import (CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType,
                                          quantize_static)
    from onnxruntime.quantization.shape_inference import quant_pre_process

    methods = {"minmax": CalibrationMethod.MinMax, "percentile": CalibrationMethod.Percentile}
    if method not in methods:
        raise AgoInputError("calibration method", f"{method!r}; expected one of {sorted(methods)}")
    if uncalibrated_range is None:
        check_feeds(fp32_path, feeds)

    class Feeds(CalibrationDataReader):
        def __init__(self):
            self.it = iter(feeds)

        def get_next(self):
            return next(self.it, None)

    with tempfile.TemporaryDirectory(prefix="ago-qdq-") as tmp, atomic_path(out_path) as part, _quiet_root_logger():
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(fp32_path), str(pre))
        cache = None
        if uncalibrated_range is not None:
            cache = Path(tmp) / "ranges.json"
            _write_fixed_ranges(pre, cache, uncalibrated_range)
        import onnx

        sampled = sampled_feature_convs(onnx.load(str(pre), load_external_data=False).graph)
        exclude = list(dict.fromkeys([*(keep_float or []), *sampled]))
        quantize_static(str(pre), str(part), None if cache else Feeds(), quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                        reduce_range=False,
                        calibrate_method=CalibrationMethod.MinMax if cache else methods[method],
                        op_types_to_quantize=STATIC_OP_TYPES, nodes_to_exclude=exclude,
                        calibration_cache_path=cache)
    return Path(out_path)


def sampled_feature_convs(graph) -> list[str]:
    """The Conv nodes of an ONNX graph that make the features a GridSample reads, in two steps: the convolutions
    whose output reaches a GridSample's input through data-movement ops only (DATA_MOVEMENT_OPS; in planes.onnx
    the TPV encoder's value projections), then those whose output reaches one of the first through such ops
    only (the FPN outputs: concatenated, padded and transposed into the cameras' mosaic). Kept in float32 by
    quantize_planes_static (the module doc says why)."""
    users: dict[str, list] = {}
    for node in graph.node:
        for name in node.input:
            users.setdefault(name, []).append(node)

    def reaches(conv, is_target) -> bool:
        tensors, seen = [conv.output[0]], set()
        while tensors:
            tensor = tensors.pop()
            for user in users.get(tensor, []):
                if user.input[0] == tensor and is_target(user):
                    return True
                if user.op_type in DATA_MOVEMENT_OPS and user.name not in seen:
                    seen.add(user.name)
                    tensors.extend(user.output)
        return False

    convs = [n for n in graph.node if n.op_type == "Conv"]
    first = {c.name for c in convs if reaches(c, lambda n: n.op_type == "GridSample")}
    second = {c.name for c in convs if c.name not in first
              and reaches(c, lambda n: n.op_type == "Conv" and n.name in first)}
    return [c.name for c in convs if c.name in first | second]


def node_module(node_name: str, module_names: set[str]) -> str | None:
    """The torch module an exported node came from, or None. torch.onnx names a node by its scopes, one per module
    that ran ("/backbone/stage8.0/_expand_conv/Conv", "/backbone/convs.0/convs.0.0/Conv"), each named relative to
    an enclosing module that is not a plain container; so each scope is looked up under the modules found so far,
    innermost first."""
    found: list[str] = []
    for scope in node_name.strip("/").split("/")[:-1]:
        for base in [*reversed(found), ""]:
            name = f"{base}.{scope}" if base else scope
            if name in module_names:
                found.append(name)
                break
        else:
            return None
    return found[-1] if found else None


def in_modules(module: str | None, modules: tuple[str, ...] | list[str]) -> bool:
    """Whether `module` is one of `modules` or inside one ("backbone.stage8" holds "backbone.stage8.0.conv")."""
    return module is not None and any(module == m or module.startswith(m + ".") for m in modules)


def convs_in_modules(planes: str | Path, module_names: set[str], modules: tuple[str, ...] | list[str]) -> list[str]:
    """The Conv nodes of an exported planes graph that come from `modules` (torch module names of the exported
    model, whose every module name is in `module_names`; e.g. "backbone.stem", "backbone.stage8": the backbone's
    first layers, the ones int8 hurts most). Each of `modules` must own one at least: else an AgoInputError (the
    TPV encoder's convolutions are traced as functional ops and belong to no module)."""
    import onnx

    nodes = [n.name for n in onnx.load(str(planes), load_external_data=False).graph.node if n.op_type == "Conv"]
    owner = {n: node_module(n, module_names) for n in nodes}
    for m in modules:
        if not any(in_modules(owner[n], (m,)) for n in nodes):
            raise AgoInputError("--int8-float", f"{m!r}: none of its convolutions is a Conv node of the exported "
                                "planes graph (the TPV encoder's are functional, /tpv/Conv*); name backbone or fpn "
                                "modules")
    return [n for n in nodes if in_modules(owner[n], modules)]


def check_float_modules(model, modules: tuple[str, ...] | list[str], option: str = "--int8-float") -> None:
    """Each name of `modules` must name a module of `model` that holds a convolution (before any export work: a
    misspelt name must not quietly quantise everything)."""
    import torch

    convs = [name for name, m in model.named_modules() if isinstance(m, torch.nn.Conv2d)]
    for m in modules:
        if not any(in_modules(c, (m,)) for c in convs):
            tops = sorted({".".join(c.split(".")[:2]) for c in convs})
            raise AgoInputError(option, f"{m!r} is no module of the model holding a convolution (modules with "
                                f"convolutions: {', '.join(tops[:12])}{' ...' if len(tops) > 12 else ''})")


def quantize_int8_graphs(folder: str | Path, files: dict[str, str], stage_keys: list[str],
                         feeds: list[dict[str, np.ndarray]], keep_float: list[str] | None = None) -> dict[str, str]:
    """Write the int8 variant of a bundle's graphs into `folder` -> {"<key>_int8": file name} for the bundle's
    file table. files: the bundle's {key: file name} ("planes" and each of stage_keys); feeds: the planes
    graph's calibration feeds (ago_export.calibration_frames.planes_feeds of training frames); keep_float:
    planes Conv node names left in float32 (`convs_in_modules`)."""
    folder = Path(folder)
    out = {"planes_int8": "planes.int8.onnx"}
    quantize_planes_static(folder / files["planes"], folder / out["planes_int8"], feeds, keep_float=keep_float)
    for key in stage_keys:
        out[f"{key}_int8"] = f"{key}.int8.onnx"
        quantize_encoder(folder / files[key], folder / out[f"{key}_int8"])
    return out


def _write_fixed_ranges(graph_path: Path, cache: Path, value_range: tuple[float, float]) -> None:
    """onnxruntime's calibration cache with one range for the activations of every Conv and Clip ([0, 6]
    for a Clip's output)."""
    import onnx
    from onnxruntime.quantization.calibrate import CalibrationMethod, TensorData, TensorsData, save_tensors_data

    graph = onnx.load(str(graph_path)).graph
    weights = {i.name for i in graph.initializer}
    ranges = {}
    for node in graph.node:
        if node.op_type in STATIC_OP_TYPES:
            for name in (node.input[0], node.output[0]):
                if name not in weights and name not in ranges:
                    lo, hi = (0.0, 6.0) if node.op_type == "Clip" and name == node.output[0] else value_range
                    ranges[name] = TensorData(lowest=np.float32(lo), highest=np.float32(hi))
    save_tensors_data(TensorsData(CalibrationMethod.MinMax, ranges), cache)
