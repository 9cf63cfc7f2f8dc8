"""Execution-provider selection (`--device`): what each device asks onnxruntime for, and the refusals
that replace a silent fall-back to the CPU. Runs on the CPU: the providers a GPU build would list are given."""

import pytest

from ago_runtime.errors import AgoInputError
from ago_runtime.providers import (Device, Precision, check_device, check_int8, check_session, openvino_target,
                                   parse_device, parse_precision, provider_list, provider_tag, stage_target)

CPU_ONLY = ["AzureExecutionProvider", "CPUExecutionProvider"]
GPU_BUILD = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]


def test_parse_names_and_refuses_typos():
    assert parse_device(" CUDA ") is Device.CUDA
    assert parse_precision("fp16") is Precision.FP16
    with pytest.raises(AgoInputError, match=r"--device.*unknown device 'gpu' \(one of: cpu, cuda, tensorrt, openvino\)"):
        parse_device("gpu")
    with pytest.raises(AgoInputError, match="--precision"):
        parse_precision("int4")


def test_cpu_build_refuses_cuda_naming_what_to_install():
    check_device(Device.CPU, available=CPU_ONLY)
    for device in (Device.CUDA, Device.TENSORRT):
        with pytest.raises(AgoInputError) as e:
            check_device(device, available=CPU_ONLY)
        message = str(e.value)
        assert message.startswith("--device: ") and "install:" in message and "\n" not in message
        assert "scripts/setup.sh --device" in message


def test_gpu_build_takes_cuda_and_tensorrt():
    check_device(Device.CUDA, available=GPU_BUILD)
    check_device(Device.TENSORRT, Precision.FP16, available=GPU_BUILD)
    with pytest.raises(AgoInputError, match="CUDA provider beside it"):
        check_device(Device.TENSORRT, available=["TensorrtExecutionProvider", "CPUExecutionProvider"])


def test_fp16_and_bf16_only_where_a_runtime_makes_them():
    for device in (Device.CPU, Device.CUDA):
        with pytest.raises(AgoInputError, match="--precision: fp16 runs through TensorRT or OpenVINO"):
            check_device(device, Precision.FP16, available=GPU_BUILD)
    for device in (Device.CPU, Device.CUDA, Device.TENSORRT):
        with pytest.raises(AgoInputError, match="--precision: bf16 runs through OpenVINO on a CPU with avx512_bf16 "
                                                "or amx_bf16, not " + device.value):
            check_device(device, Precision.BF16, available=GPU_BUILD)


def test_provider_lists():
    assert provider_list(Device.CPU) == ["CPUExecutionProvider"]
    trt = provider_list(Device.TENSORRT, Precision.FP16, engine_cache="/tmp/engines")
    assert trt[0][0] == "TensorrtExecutionProvider" and trt[0][1]["trt_fp16_enable"] is True
    assert trt[0][1]["trt_engine_cache_path"] == "/tmp/engines"
    assert trt[1] == "CUDAExecutionProvider"          # TensorRT's unsupported nodes go to CUDA, not the CPU
    assert "CPUExecutionProvider" not in [p if isinstance(p, str) else p[0] for p in trt]
    assert provider_tag(Device.CPU) == "cpu" and provider_tag(Device.TENSORRT, Precision.FP16) == "tensorrt-fp16"


class _Session:
    def __init__(self, providers):
        self._providers = providers

    def get_providers(self):
        return self._providers


def test_a_session_that_fell_back_to_the_cpu_is_refused():
    check_session(_Session(["CUDAExecutionProvider", "CPUExecutionProvider"]), Device.CUDA, "planes.onnx")
    with pytest.raises(AgoInputError, match=r"^planes.onnx: onnxruntime could not start CUDAExecutionProvider"):
        check_session(_Session(["CPUExecutionProvider"]), Device.CUDA, "planes.onnx")


def test_openvino_always_states_its_precision():
    # on a CPU with bf16 units OpenVINO's CPU device runs bf16 unless told otherwise: fp32 must ask for f32
    assert openvino_target(Precision.FP32) == ("CPU", {"INFERENCE_PRECISION_HINT": "f32", "PERFORMANCE_HINT": "LATENCY"})
    assert openvino_target(Precision.BF16)[1]["INFERENCE_PRECISION_HINT"] == "bf16"
    assert openvino_target(Precision.FP16) == ("GPU", {"INFERENCE_PRECISION_HINT": "f16"})
    with pytest.raises(ValueError):
        provider_list(Device.OPENVINO)        # not an onnxruntime provider: ago_runtime/openvino_session.py


from conftest import ago_in_process  # noqa: E402

_ago = ago_in_process


def test_infer_refuses_a_missing_provider_before_any_work(tmp_path):
    out = tmp_path / "out"
    code, err = _ago(["demo", "--device", "cuda", "--out", out])
    assert code == 2
    assert err.startswith("error: --device: cuda needs onnxruntime's CUDAExecutionProvider")
    assert not out.exists()                              # nothing written
    code, err = _ago(["infer", "--images", tmp_path, "--precision", "fp16", "--out", out])
    assert code == 2 and err.startswith("error: --precision:")
    code, err = _ago(["retrieve", "--phrase", "car", "--images", tmp_path, "--device", "gpu", "--out", out])
    assert code == 2 and err.startswith("error: --device: 'gpu' is not one of 'cpu', 'cuda'")   # the Enum's check
    assert not out.exists()


@pytest.mark.filterwarnings("ignore:Specified provider")
def test_a_listed_provider_that_cannot_start_is_refused_not_run_on_the_cpu(monkeypatch, tmp_path):
    """onnxruntime-gpu lists CUDA even where its libraries are missing; the Predictor must refuse then,
    never run the frame on the CPU while the user asked for the GPU."""
    import onnxruntime as ort

    from ago_runtime.predict.bundle import resolve_bundle
    from ago_runtime.predict.predictor import Predictor

    monkeypatch.setenv("AGO_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(ort, "get_available_providers", lambda: GPU_BUILD)
    with pytest.raises(AgoInputError, match=r"planes\.onnx: "):
        Predictor(resolve_bundle(None), device="cuda", warm_up=False)


def test_the_cpu_cache_key_names_the_provider():
    from ago_runtime.cache import optimized_cache_path

    assert "-cpu-" in optimized_cache_path("ab" * 32).name


def test_int8_runs_on_a_cpu_and_openvino_keeps_the_voxel_stages_on_onnxruntime():
    # OpenVINO's CPU device runs the planes graph; the per-slab voxel stages stay on onnxruntime's CPU provider
    assert stage_target(Device.OPENVINO, Precision.FP32) == (Device.CPU, Precision.FP32)
    assert stage_target(Device.OPENVINO, Precision.BF16) == (Device.CPU, Precision.FP32)
    assert stage_target(Device.OPENVINO, Precision.FP16) == (Device.OPENVINO, Precision.FP16)   # its GPU device
    assert stage_target(Device.CUDA, Precision.FP32) == (Device.CUDA, Precision.FP32)
    assert stage_target(Device.TENSORRT, Precision.FP16) == (Device.TENSORRT, Precision.FP16)
    for device, precision in [(Device.CPU, Precision.FP32), (Device.OPENVINO, Precision.FP32),
                              (Device.OPENVINO, Precision.BF16)]:
        check_int8(device, precision)
    with pytest.raises(AgoInputError, match=r"^--int8: the int8 graphs run on a CPU \(--device cpu, or --device "
                                            r"openvino with --precision fp32 or bf16\), not --device cuda$"):
        check_int8(Device.CUDA, Precision.FP32)
    with pytest.raises(AgoInputError, match=r"not --device openvino --precision fp16$"):
        check_int8(Device.OPENVINO, Precision.FP16)
    with pytest.raises(AgoInputError, match=r"not --device tensorrt$"):
        check_int8(Device.TENSORRT, Precision.FP16)
