"""Which onnxruntime execution provider runs the bundle's graphs (`--device cpu|cuda|tensorrt|openvino`).

The encoder graphs are plain ONNX and run wherever onnxruntime runs; the text-bank products, the
folded heads and the open-world identifier are numpy and stay on the CPU (docs/runtime.md, "Devices").

- `Device`: the four devices a user can name, each with the provider list handed to onnxruntime.
  TensorRT lists the CUDA provider after it: onnxruntime gives the nodes TensorRT cannot build to the
  next provider in the list, and without CUDA there that would be the CPU.
- `check_device(device)`: refuses, before any work, a device whose provider this onnxruntime build does
  not have, naming what to install (never a silent fall-back to the CPU).
- `check_session(session, device, path, precision)`: refuses a session onnxruntime made on another provider
  than the one asked for (onnxruntime-gpu lists CUDA even when the CUDA libraries are missing, then quietly
  builds a CPU session; OpenVINO's CPU device does not start with fp16, see `openvino_options`).
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


MAIN_PROVIDER = {
    Device.CPU: "CPUExecutionProvider",
    Device.CUDA: "CUDAExecutionProvider",
    Device.TENSORRT: "TensorrtExecutionProvider",
    Device.OPENVINO: "OpenVINOExecutionProvider",
}

# What to install for each device. onnxruntime's GPU and OpenVINO builds replace the CPU build (they
# ship the same `onnxruntime` module), so the CPU wheel is removed first; scripts/setup.sh --device does it.
INSTALL = {
    Device.CUDA: "bash scripts/setup.sh --device cuda (pip uninstall onnxruntime; "
                 "pip install 'onnxruntime-gpu>=1.17,<1.33'; needs the CUDA 12 and cuDNN 9 libraries)",
    Device.TENSORRT: "bash scripts/setup.sh --device cuda, and TensorRT 10 libraries on LD_LIBRARY_PATH",
    Device.OPENVINO: "bash scripts/setup.sh --device openvino (pip uninstall onnxruntime; "
                     "pip install 'onnxruntime-openvino>=1.17,<1.33')",
}


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
    """The `providers=` argument for onnxruntime.InferenceSession. `engine_cache`: a folder where
    TensorRT keeps the engines it builds (building one takes minutes; later sessions load it)."""
    if device is Device.CPU:
        return ["CPUExecutionProvider"]
    if device is Device.CUDA:
        return ["CUDAExecutionProvider"]
    if device is Device.TENSORRT:
        options = {"trt_fp16_enable": precision is Precision.FP16}
        if engine_cache is not None:
            options.update(trt_engine_cache_enable=True, trt_engine_cache_path=str(engine_cache))
        return [("TensorrtExecutionProvider", options), "CUDAExecutionProvider"]
    return [("OpenVINOExecutionProvider", openvino_options(precision))]


def openvino_options(precision: Precision = Precision.FP32) -> dict:
    """OpenVINO's device for a precision: its CPU device runs fp32 only (it does not start with FP16), so fp16
    asks for OpenVINO's GPU device (an Intel GPU); on a machine without one the session falls back and
    `check_session` refuses it."""
    if precision is Precision.FP16:
        return {"device_type": "GPU", "precision": "FP16"}
    return {"device_type": "CPU", "precision": "FP32"}


def check_device(device: Device, precision: Precision = Precision.FP32,
                 available: list[str] | None = None) -> None:
    """Refuse a device this onnxruntime cannot run, or a precision it does not take, with what to do."""
    import onnxruntime as ort   # here, so that the CLI's option types (Device, Precision) cost no onnxruntime import

    available = ort.get_available_providers() if available is None else available
    if precision is Precision.FP16 and device in (Device.CPU, Device.CUDA):
        raise AgoInputError("--precision", f"fp16 runs through TensorRT or OpenVINO, not {device.value} "
                            "(use --device tensorrt or --device openvino, or --precision fp32)")
    needed = MAIN_PROVIDER[device]
    if needed not in available:
        have = ", ".join(p.replace("ExecutionProvider", "") for p in available) or "none"
        raise AgoInputError("--device", f"{device.value} needs onnxruntime's {needed}, which this onnxruntime "
                            f"{ort.__version__} does not have (it has: {have}); install: {INSTALL[device]}")
    if device is Device.TENSORRT and "CUDAExecutionProvider" not in available:
        raise AgoInputError("--device", f"tensorrt needs the CUDA provider beside it; install: {INSTALL[device]}")


def check_session(session, device: Device, path, precision: Precision = Precision.FP32) -> None:
    """Refuse a session whose first provider is not the one asked for (a silent fall-back)."""
    got = session.get_providers()
    if not got or got[0] != MAIN_PROVIDER[device]:
        if device is Device.OPENVINO and precision is Precision.FP16:
            hint = ("fp16 runs on OpenVINO's GPU device (an Intel GPU) and this machine has none that OpenVINO "
                    "can use; OpenVINO's CPU device runs fp32: use --precision fp32")
        else:
            hint = f"check the libraries it needs: {INSTALL.get(device, '')}"
        raise AgoInputError(path, f"onnxruntime could not start {MAIN_PROVIDER[device]} for this graph "
                            f"(it made a session on {', '.join(got) or 'nothing'}); {hint}")


def provider_tag(device: Device, precision: Precision = Precision.FP32) -> str:
    """Names the provider in cache keys: an optimised graph holds provider-specific layouts and fusions."""
    return device.value if precision is Precision.FP32 else f"{device.value}-{precision.value}"
