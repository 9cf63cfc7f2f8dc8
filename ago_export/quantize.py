"""Dynamic int8 quantisation of an exported encoder (onnxruntime.quantization.quantize_dynamic).

Takes an fp32 ONNX file; writes an ONNX file whose MatMul/Gemm weights are int8 (activations are
quantised on the fly per batch). Convolutions and GridSample stay float32. The result is parity-
checked by the exporter against the looser INT8_TOLERANCE (ago_export.parity).
"""

from __future__ import annotations

from pathlib import Path


def quantize_encoder(fp32_path: str | Path, int8_path: str | Path) -> Path:
    import logging

    from onnxruntime.quantization import QuantType, quantize_dynamic

    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)   # quantize_dynamic logs a pre-processing hint on the root logger
    try:
        quantize_dynamic(str(fp32_path), str(int8_path), weight_type=QuantType.QInt8,
                         op_types_to_quantize=["MatMul", "Gemm"])
    finally:
        root.setLevel(level)
    return Path(int8_path)
