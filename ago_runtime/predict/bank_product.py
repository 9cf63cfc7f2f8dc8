"""The folded bank's product with hidden features, s = A x^T, as an onnxruntime session the runtime builds itself.

The bank changes with every prompt file, so its product cannot live in the exported graphs; onnxruntime's
GEMM runs this skinny product (P+1 rows x D x a few thousand voxels) several times faster than numpy's
BLAS here. The graph is one Gemm node without weights (inputs `bank` (P', d), `x` (n, d), transB = 1 ->
`s` (P', n), every dimension symbolic), so it is written here as ONNX protobuf bytes: no graph file ships
with the runtime or a bundle, and the runtime needs no `onnx` package (tests/test_decision.py checks the
bytes with onnx.checker).
"""

from __future__ import annotations

import numpy as np
import onnxruntime as ort

from ago_runtime.cache import session_options

OPSET = 17
IR_VERSION = 8
_FLOAT = 1          # onnx TensorProto.FLOAT
_ATTR_INT = 2       # onnx AttributeProto.INT


# ---- a few protobuf encoders (wire types 0: varint, 2: length-delimited) ------------------------
def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        byte, n = n & 0x7F, n >> 7
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _int(field: int, value: int) -> bytes:
    return _varint(field << 3) + _varint(value)


def _bytes(field: int, payload: bytes | str) -> bytes:
    payload = payload.encode() if isinstance(payload, str) else payload
    return _varint(field << 3 | 2) + _varint(len(payload)) + payload


def _tensor_value(name: str, dims: list[str]) -> bytes:
    """ValueInfoProto: a float tensor with symbolic dimensions."""
    shape = b"".join(_bytes(1, _bytes(2, d)) for d in dims)                    # TensorShapeProto.dim.dim_param
    tensor_type = _int(1, _FLOAT) + _bytes(2, shape)                           # TypeProto.Tensor
    return _bytes(1, name) + _bytes(2, _bytes(1, tensor_type))                 # name, type.tensor_type


def bank_product_model_bytes() -> bytes:
    """ModelProto bytes of s = Gemm(bank, x, transB=1)."""
    trans_b = _bytes(1, "transB") + _int(3, 1) + _int(20, _ATTR_INT)            # AttributeProto name, i, type
    node = _bytes(1, "bank") + _bytes(1, "x") + _bytes(2, "s") + _bytes(3, "bank_product") + _bytes(4, "Gemm") \
        + _bytes(5, trans_b)
    graph = (_bytes(1, node) + _bytes(2, "ago_bank_product")
             + _bytes(11, _tensor_value("x", ["voxels", "width"]))
             + _bytes(11, _tensor_value("bank", ["phrases", "width"]))
             + _bytes(12, _tensor_value("s", ["phrases", "voxels"])))
    opset = _bytes(1, "") + _int(2, OPSET)
    return _int(1, IR_VERSION) + _bytes(2, "ago_runtime.predict.bank_product") + _bytes(7, graph) + _bytes(8, opset)


class BankProduct:
    """s = bank x^T (P', n) for any bank (P', d) and features x (n, d), float32, in onnxruntime."""

    def __init__(self, threads: int | None = None):
        self.session = ort.InferenceSession(bank_product_model_bytes(), session_options(threads),
                                            providers=["CPUExecutionProvider"])

    def __call__(self, bank: np.ndarray, x: np.ndarray) -> np.ndarray:
        if x.shape[0] == 0:
            return np.zeros((bank.shape[0], 0), np.float32)
        (s,) = self.session.run(["s"], {"x": x, "bank": bank})
        return s
