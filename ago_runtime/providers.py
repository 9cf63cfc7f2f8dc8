"""Which runtime runs the bundle's graphs (`--device cpu|cuda|tensorrt|openvino`, `--precision fp32|fp16|bf16`).

The encoder graphs are plain ONNX and run wherever onnxruntime runs; the text-bank products, the
folded heads and the open-world identifier are numpy and stay on the CPU (docs/runtime.md, "Devices").

- `Device`: the four devices a user can name. cpu, cuda and tensorrt are onnxruntime execution providers
  (`provider_list`); TensorRT lists the CUDA provider after it: onnxruntime gives the nodes TensorRT cannot
  build to the next provider in the list, and without CUDA there that would be the CPU. openvino is the
  OpenVINO runtime itself (the `openvino` package, the `openvino` extra, beside onnxruntime's CPU build;
  ago_runtime/openvino_session.py), which reads the same ONNX files.
- `Precision`: fp32 everywhere; fp16 through TensorRT or OpenVINO's GPU device; bf16 through OpenVINO's CPU
  device on a CPU with bf16 units (`BF16_FLAGS`; onnxruntime's CPU provider has no bf16 convolution or MatMul).
- `check_device(device, precision)`: refuses, before any work, a device or precision this machine cannot run,
  naming what to install or what to use instead (never a silent fall-back to the CPU or to fp32).
- `check_session(session, device, path)`: refuses an onnxruntime session made on another provider than the
  one asked for (onnxruntime-gpu lists CUDA even when the CUDA libraries are missing, then quietly builds a
  CPU session).
- `openvino_target(precision)`: OpenVINO's device and its compile settings for a precision.
- `stage_target(device, precision)`: where the per-voxel stages run (the planes graph runs on `device`).
- `check_int8(device, precision)`: refuses `--int8` where the int8 graphs cannot run (they need a CPU).
- `provider_tag(device, precision)`: the part of the optimised-graph cache key that names the provider.
"""

from __future__ import annotations

from enum import Enum

from ago_runtime.errors import AgoInputError


class Device(str, Enum):
    CPU = "cpu"
    CUDA = "cuda"
    TENSORRT = "tensorrt"
    OPENVINO = "openvino"


class Precision(str, Enum):
    FP32 = "fp32"
    FP16 = "fp16"
    BF16 = "bf16"


MAIN_PROVIDER = {
    Device.CPU: "CPUExecutionProvider",
    Device.CUDA: "CUDAExecutionProvider",
    Device.TENSORRT: "TensorrtExecutionProvider",
}

# What to install for each device. onnxruntime's GPU build replaces the CPU build (both ship the same
# `onnxruntime` module), so the CPU wheel is removed first; scripts/setup.sh --device does it. OpenVINO is a
# package of its own beside onnxruntime.
INSTALL = {
    Device.CUDA: "bash scripts/setup.sh --device cuda (pip uninstall onnxruntime; "
                 "pip install 'onnxruntime-gpu>=1.17,<1.33'; needs the CUDA 12 and cuDNN 9 libraries)",
    Device.TENSORRT: "bash scripts/setup.sh --device cuda, and TensorRT 10 libraries on LD_LIBRARY_PATH",
    Device.OPENVINO: "bash scripts/setup.sh --device openvino (pip install 'openvino>=2026.4,<2026.5', "
                     "the `openvino` extra of ago)",
}

# The CPU instruction sets that give OpenVINO bf16 kernels (Linux /proc/cpuinfo names): AVX512-BF16 or AMX.
BF16_FLAGS = ("avx512_bf16", "amx_bf16")


def _parse(kind: type[Enum], value, option: str, what: str):
    """`value` (a member or its name, any case) -> a member of `kind`; else one line naming `option`."""
    if isinstance(value, kind):
        return value
    try:
        return kind(str(value).strip().lower())
    except ValueError:
        names = ", ".join(m.value for m in kind)
        raise AgoInputError(option, f"unknown {what} {value!r} (one of: {names})") from None


def parse_device(value: "str | Device", option: str = "--device") -> Device:
    return _parse(Device, value, option, "device")


def parse_precision(value: "str | Precision", option: str = "--precision") -> Precision:
    return _parse(Precision, value, option, "precision")


def provider_list(device: Device, precision: Precision = Precision.FP32, engine_cache=None) -> list:
    """The `providers=` argument for onnxruntime.InferenceSession (cpu, cuda, tensorrt; openvino is not an
    onnxruntime provider here: `openvino_target`). `engine_cache`: a folder where TensorRT keeps the engines
    it builds (building one takes minutes; later sessions load it)."""
    if device is Device.CPU:
        return ["CPUExecutionProvider"]
    if device is Device.CUDA:
        return ["CUDAExecutionProvider"]
    if device is Device.TENSORRT:
        options = {"trt_fp16_enable": precision is Precision.FP16}
        if engine_cache is not None:
            options.update(trt_engine_cache_enable=True, trt_engine_cache_path=str(engine_cache))
        return [("TensorrtExecutionProvider", options), "CUDAExecutionProvider"]
    raise ValueError(f"{device.value} is not an onnxruntime provider here (ago_runtime/openvino_session.py)")


def openvino_target(precision: Precision = Precision.FP32) -> tuple[str, dict]:
    """(OpenVINO device, compile settings) for a precision. The precision is always stated: on a CPU with
    bf16 units OpenVINO's CPU device runs bf16 unless told otherwise, so fp32 asks for f32. fp16 runs on
    OpenVINO's GPU device (an Intel GPU); its CPU device has no fp16 inference precision."""
    if precision is Precision.FP16:
        return "GPU", {"INFERENCE_PRECISION_HINT": "f16"}
    hint = "bf16" if precision is Precision.BF16 else "f32"
    return "CPU", {"INFERENCE_PRECISION_HINT": hint, "PERFORMANCE_HINT": "LATENCY"}


def stage_target(device: Device, precision: Precision) -> tuple[Device, Precision]:
    """Where the voxel stages run when the planes graph runs on (device, precision). With OpenVINO on the CPU
    (fp32, bf16) they run on onnxruntime's CPU provider in fp32: small per-slab graphs, which onnxruntime runs
    in parallel slabs faster than OpenVINO does (benchmarks/results/bf16_openvino.md), so OpenVINO's gain is
    the planes graph's. Every other device runs both."""
    if device is Device.OPENVINO and openvino_target(precision)[0] == "CPU":
        return Device.CPU, Precision.FP32
    return device, precision


def check_int8(device: Device, precision: Precision) -> None:
    """The int8 variant (`ago export --int8`) runs on a CPU: onnxruntime's CPU provider, or OpenVINO's CPU device
    for its planes graph (int8 kernels from the QDQ nodes; the rest of the graph at `precision`) with the voxel
    stages on onnxruntime's CPU provider (`stage_target`). Refused with one line elsewhere."""
    if stage_target(device, precision)[0] is not Device.CPU:
        where = f"--device {device.value}" + (f" --precision {precision.value}" if device is Device.OPENVINO else "")
        raise AgoInputError("--int8", f"the int8 graphs run on a CPU (--device cpu, or --device openvino with "
                            f"--precision fp32 or bf16), not {where}")


def cpu_flags() -> set[str]:
    """The instruction-set flags of this CPU (/proc/cpuinfo's first `flags` line; empty where there is none)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def openvino_installed() -> bool:
    import importlib.util

    return importlib.util.find_spec("openvino") is not None


def check_openvino(precision: Precision) -> None:
    """Refuse `--device openvino` without the openvino package, bf16 on a CPU without bf16 units, fp16 where
    OpenVINO finds no GPU device: one line naming the option."""
    option = "--device" if precision is Precision.FP32 else "--precision"
    if not openvino_installed():
        raise AgoInputError(option, f"{'openvino' if precision is Precision.FP32 else precision.value} runs "
                            f"through the OpenVINO runtime, which is not installed; install: {INSTALL[Device.OPENVINO]}")
    if precision is Precision.BF16:
        if not set(BF16_FLAGS) & cpu_flags():
            raise AgoInputError("--precision", f"bf16 needs a CPU with {' or '.join(BF16_FLAGS)} and this CPU has "
                                "neither (OpenVINO would emulate it, slower than fp32); use --precision fp32")
    if precision is Precision.FP16:
        import openvino as ov

        devices = ov.Core().available_devices
        if not any(d.startswith("GPU") for d in devices):
            raise AgoInputError("--precision", "fp16 runs on OpenVINO's GPU device (an Intel GPU) and OpenVINO "
                                f"finds none here (it has: {', '.join(devices) or 'none'}); use --precision bf16 "
                                "on a CPU with bf16 units, or fp32")


def check_device(device: Device, precision: Precision = Precision.FP32,
                 available: list[str] | None = None) -> None:
    """Refuse a device this machine cannot run, or a precision it does not take, with what to do."""
    if precision is Precision.BF16 and device is not Device.OPENVINO:
        raise AgoInputError("--precision", f"bf16 runs through OpenVINO on a CPU with {' or '.join(BF16_FLAGS)}, "
                            f"not {device.value} (use --device openvino --precision bf16, or --precision fp32)")
    if precision is Precision.FP16 and device in (Device.CPU, Device.CUDA):
        raise AgoInputError("--precision", f"fp16 runs through TensorRT or OpenVINO, not {device.value} "
                            "(use --device tensorrt or --device openvino, or --precision fp32)")
    if device is Device.OPENVINO:
        return check_openvino(precision)
    import onnxruntime as ort   # here, so that the CLI's option types (Device, Precision) cost no onnxruntime import

    available = ort.get_available_providers() if available is None else available
    needed = MAIN_PROVIDER[device]
    if needed not in available:
        have = ", ".join(p.replace("ExecutionProvider", "") for p in available) or "none"
        raise AgoInputError("--device", f"{device.value} needs onnxruntime's {needed}, which this onnxruntime "
                            f"{ort.__version__} does not have (it has: {have}); install: {INSTALL[device]}")
    if device is Device.TENSORRT and "CUDAExecutionProvider" not in available:
        raise AgoInputError("--device", f"tensorrt needs the CUDA provider beside it; install: {INSTALL[device]}")


def check_session(session, device: Device, path) -> None:
    """Refuse an onnxruntime session whose first provider is not the one asked for (a silent fall-back)."""
    got = session.get_providers()
    if not got or got[0] != MAIN_PROVIDER[device]:
        raise AgoInputError(path, f"onnxruntime could not start {MAIN_PROVIDER[device]} for this graph "
                            f"(it made a session on {', '.join(got) or 'nothing'}); check the libraries it "
                            f"needs: {INSTALL.get(device, '')}")


def provider_tag(device: Device, precision: Precision = Precision.FP32) -> str:
    """Names the provider in cache keys: an optimised graph holds provider-specific layouts and fusions."""
    return device.value if precision is Precision.FP32 else f"{device.value}-{precision.value}"
