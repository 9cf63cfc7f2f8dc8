"""ago's cache folder and onnxruntime sessions whose optimised graph is cached there (a basic module:
imports only onnxruntime, ago_runtime.errors and ago_runtime.providers).

- `ago_cache_dir()`: $AGO_CACHE_DIR or ~/.cache/ago (banks, text encoder, optimised graphs, ...);
- `open_session(path, threads, sha256, device)`: an onnxruntime session, on the CPU by default; with the
  file's sha256 the optimised CPU graph is saved under `ago_cache_dir()/ort/` (keyed by graph, onnxruntime
  version, provider and CPU) by the first session and loaded with graph optimisation off by later ones,
  which then open several times faster; another device: `open_device_session` (onnxruntime's CUDA and
  TensorRT providers) or, for `--device openvino`, ago_runtime.openvino_session (its compiled graphs cached
  under `ago_cache_dir()/openvino/`);
- `session_options(threads, optimize)`: the runtime's options (idle worker threads do not spin; no memory pattern).
"""

from __future__ import annotations

import hashlib
import os
import platform
import tempfile
from pathlib import Path

import onnxruntime as ort

from ago_runtime.errors import AgoInputError
from ago_runtime.providers import Device, Precision, check_device, check_session, provider_list, provider_tag

ENV_NO_ORT_CACHE = "AGO_NO_ORT_CACHE"   # =1: never read or write cached optimised graphs


def ago_cache_dir() -> Path:
    """Root of ago's caches: $AGO_CACHE_DIR or ~/.cache/ago."""
    env = os.environ.get("AGO_CACHE_DIR")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "ago"


def session_options(threads: int | None = None, optimize: bool = True) -> ort.SessionOptions:
    so = ort.SessionOptions()
    so.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimize
                                   else ort.GraphOptimizationLevel.ORT_DISABLE_ALL)
    if threads:
        so.intra_op_num_threads = int(threads)
    # onnxruntime's idle worker threads spin by default; between the slabs they then steal the cores
    # that numpy's heads need (frames are faster with spinning off on a 2-core machine).
    # AGO_ORT_SPIN=1 turns spinning back on.
    if os.environ.get("AGO_ORT_SPIN", "0") != "1":
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    # onnxruntime's memory pattern plans one arena block per input shape from the runs it has seen; the planes
    # graph's sample tensors change size with what the cameras see (it samples only those entries), and with the
    # pattern on, the first real frame after the warm-up ran 1.8-2.5x slower than later ones and the peak RSS
    # was 1.5x (benchmarks/results/mem_pattern.md); without it first and steady frames match.
    so.enable_mem_pattern = False
    so.log_severity_level = 3
    return so


def _cpu_tag() -> str:
    """A short tag of this CPU (model and instruction-set flags): optimised graphs hold CPU-specific
    layouts (onnxruntime's NCHWc blocks), so the cache never shares them across CPUs."""
    text = platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith(("model name", "flags", "Features")):
                    text += line
                if line.strip() == "":
                    break
    except OSError:
        pass
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def optimized_cache_path(sha256: str, device: Device = Device.CPU) -> Path:
    """Keyed by the graph, onnxruntime's version, the provider and this CPU."""
    return ago_cache_dir() / "ort" / f"{sha256[:32]}-ort{ort.__version__}-{provider_tag(device)}-{_cpu_tag()}.onnx"


def _create(path: Path, so: ort.SessionOptions, providers=("CPUExecutionProvider",)) -> ort.InferenceSession:
    try:
        return ort.InferenceSession(str(path), so, providers=list(providers))
    except Exception as e:  # onnxruntime raises its own Fail/InvalidProtobuf types
        raise AgoInputError(path, f"onnxruntime cannot load the graph ({str(e).splitlines()[0][:200]})") from None


def open_device_session(path: Path, threads: int | None, sha256: str | None, device: Device,
                        precision: Precision = Precision.FP32) -> ort.InferenceSession:
    """An onnxruntime session on an accelerator (`--device cuda|tensorrt`). onnxruntime optimises the graph for
    that provider in memory each time (an optimised graph saved for one provider may hold nodes only it
    runs); TensorRT keeps the engines it builds under ago_cache_dir()/trt/<graph>-<precision>/. Refused,
    naming what to install, when the provider is missing or onnxruntime starts another one."""
    check_device(device, precision)
    engines = None
    if device is Device.TENSORRT and sha256 and os.environ.get(ENV_NO_ORT_CACHE) != "1":
        engines = ago_cache_dir() / "trt" / f"{sha256[:32]}-{provider_tag(device, precision)}"
        engines.mkdir(parents=True, exist_ok=True)
    sess = _create(path, session_options(threads), provider_list(device, precision, engines))
    check_session(sess, device, path)
    return sess


def open_session(path: Path, threads: int | None, sha256: str | None = None, device: Device = Device.CPU,
                 precision: Precision = Precision.FP32):
    """An onnxruntime session of `path`. With the graph's sha256 (from bundle.json, already checked by
    Bundle.load) the optimised graph is cached: read when present (optimisation off), else written
    while this session is made (written to a temporary name, then renamed). A cache file that
    onnxruntime cannot read is removed and remade. AGO_NO_ORT_CACHE=1 disables the cache.
    device: openvino -> an OpenVinoSession (the same interface), another accelerator -> open_device_session."""
    if device is Device.OPENVINO:
        from ago_runtime.openvino_session import open_openvino_session

        check_device(device, precision)
        cache = None if os.environ.get(ENV_NO_ORT_CACHE) == "1" else ago_cache_dir() / "openvino"
        return open_openvino_session(path, threads, precision, cache)
    if device is not Device.CPU:
        return open_device_session(path, threads, sha256, device, precision)
    if not sha256 or os.environ.get(ENV_NO_ORT_CACHE) == "1":
        return _create(path, session_options(threads))
    cached = optimized_cache_path(sha256)
    if cached.is_file():
        try:
            return ort.InferenceSession(str(cached), session_options(threads, optimize=False),
                                        providers=["CPUExecutionProvider"])
        except Exception:
            cached.unlink(missing_ok=True)
    so = session_options(threads)
    tmp = None
    try:
        cached.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{cached.stem}.", suffix=".tmp.onnx", dir=cached.parent)
        os.close(fd)
        so.optimized_model_filepath = tmp
    except OSError:
        tmp = None          # no writable cache: just optimise in memory
    try:
        sess = _create(path, so)
        if tmp is not None and os.path.getsize(tmp) > 0:
            os.replace(tmp, cached)
        return sess
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
