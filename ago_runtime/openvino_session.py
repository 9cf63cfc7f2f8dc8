"""The bundle's graphs on the OpenVINO runtime (`--device openvino [--precision fp32|bf16|fp16]`; a basic module:
imports only ago_runtime.errors and ago_runtime.providers, and `openvino` when a session is opened).

OpenVINO reads the bundle's ONNX files itself (no onnxruntime build of its own). `OpenVinoSession` offers
the part of onnxruntime's InferenceSession that the runtime uses (`get_inputs`, `get_outputs`,
`get_providers`, `run`), so the encoder, the contract's graph checks and the warm-up treat both alike.

- The precision is OpenVINO's INFERENCE_PRECISION_HINT (providers.openvino_target): bf16 runs the
  convolutions and MatMuls on the CPU's AVX512-BF16 / AMX units with fp32 inputs and outputs; fp32 is asked
  for explicitly (on such a CPU OpenVINO's default is bf16).
- Compiled graphs are cached by OpenVINO in `cache_dir` (its CACHE_DIR: keyed by graph, settings and
  device), so later sessions open faster; None: no cache.
- `run` is safe from several threads (`Predictor(workers=N)`): each thread has its own infer request.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

from ago_runtime.errors import AgoInputError
from ago_runtime.providers import Precision, openvino_target


@dataclass(frozen=True)
class GraphArg:
    """One input or output as onnxruntime's NodeArg shows it: name, shape (ints; a name for a dynamic axis),
    type ("tensor(float)" for float32)."""

    name: str
    shape: list
    type: str


def _arg(port) -> GraphArg:
    shape = [d.get_length() if d.is_static else "?" for d in port.get_partial_shape()]
    kind = port.get_element_type().get_type_name()          # "f32", "bf16", ...
    return GraphArg(port.get_any_name(), shape, "tensor(float)" if kind == "f32" else f"tensor({kind})")


class OpenVinoSession:
    """A compiled OpenVINO model with onnxruntime's session interface (see the module doc)."""

    def __init__(self, compiled, device_name: str, precision: Precision):
        self.compiled = compiled
        self.device_name = device_name
        self.precision = precision
        self._inputs = [_arg(p) for p in compiled.inputs]
        self._outputs = [_arg(p) for p in compiled.outputs]
        self._out_index = {a.name: i for i, a in enumerate(self._outputs)}
        self._local = threading.local()

    def get_inputs(self) -> list[GraphArg]:
        return list(self._inputs)

    def get_outputs(self) -> list[GraphArg]:
        return list(self._outputs)

    def get_providers(self) -> list[str]:
        return [f"OpenVINO:{self.device_name}:{self.precision.value}"]

    def run(self, output_names, feed: dict) -> list:
        """The outputs named (all when None), as numpy arrays of their own (copied out of the request)."""
        request = getattr(self._local, "request", None)
        if request is None:
            request = self._local.request = self.compiled.create_infer_request()
        result = request.infer(feed)
        names = [a.name for a in self._outputs] if output_names is None else output_names
        return [result[self.compiled.outputs[self._out_index[n]]] for n in names]


def open_openvino_session(path: Path, threads: int | None, precision: Precision = Precision.FP32,
                          cache_dir: Path | None = None) -> OpenVinoSession:
    """`path` compiled by OpenVINO for `precision` (providers.check_device has checked the package and the CPU);
    threads: OpenVINO's inference threads (None: its own choice, every core)."""
    import openvino as ov

    device_name, config = openvino_target(precision)
    config = dict(config)
    if threads:
        config["INFERENCE_NUM_THREADS"] = int(threads)
    if cache_dir is not None:
        try:
            cache_dir.mkdir(parents=True, exist_ok=True)
            config["CACHE_DIR"] = str(cache_dir)
        except OSError:
            pass            # no writable cache: compile each time
    try:
        compiled = ov.Core().compile_model(str(path), device_name, config)
    except Exception as e:  # OpenVINO raises RuntimeError with a long multi-line text
        raise AgoInputError(path, f"OpenVINO cannot compile the graph for {device_name} {precision.value} "
                            f"({str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__})") from None
    return OpenVinoSession(compiled, device_name, precision)
