"""Custom-kernel prototypes (measurement only; NOT part of the package, which stays pure pip).

Compiles two C kernels with the system's gcc (-O3 -mavx2 -mfma -fopenmp) into a temp folder, loads
them with ctypes and times them against what the runtime does today, on the same data:

1. softplus_avx2.c: a vectorised softplus (AVX2 exp + log polynomials) vs the runtime's
   numpy + OpenCV softplus (ago_runtime.predict.encoder.Softplus) and vs onnxruntime's Relu/Abs/Sigmoid/Log/Sub
   chain, on one slab's adapter pre-activation (4096 x 384);
2. deform.c: channels-last bilinear sampling fused with the attention weighting vs onnxruntime
   GridSample + Mul + ReduceSum, on the image-attention shapes of planes.onnx (4 heads x 16 channels
   over the 48 x 276 camera canvas; plane_xy: 24 points x 2500 queries, a side plane: 96 x 400,
   cross-view: 12 x 2500).

    python benchmarks/prototypes/measure.py        # needs gcc with AVX2; prints a markdown table
"""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))


def build(tmp: Path, name: str) -> ctypes.CDLL:
    out = tmp / f"lib{name}.so"
    subprocess.run(["gcc", "-O3", "-mavx2", "-mfma", "-fopenmp", "-shared", "-fPIC", str(HERE / f"{name}.c"), "-o",
                    str(out), "-lm"], check=True)
    return ctypes.CDLL(str(out))


def best(fn, reps: int = 15) -> tuple[float, float]:
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return min(ts), float(np.median(ts))


def graph(nodes, inputs, outputs, inits=()):
    import onnxruntime as ort
    from onnx import helper as H

    from ago_runtime.predict.encoder import session_options

    m = H.make_model(H.make_graph(nodes, "g", inputs, outputs, list(inits)), opset_imports=[H.make_opsetid("", 17)],
                     ir_version=9)
    return ort.InferenceSession(m.SerializeToString(), session_options(), providers=["CPUExecutionProvider"])


def main() -> None:
    from onnx import TensorProto as TP
    from onnx import helper as H

    from ago_runtime.predict.encoder import Softplus

    os.environ.setdefault("OMP_NUM_THREADS", str(os.cpu_count() or 1))
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")   # idle OpenMP threads must not spin against the others
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    V = H.make_tensor_value_info
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        sp_lib, df_lib = build(Path(tmp), "softplus_avx2"), build(Path(tmp), "deform")
        sp = sp_lib.softplus_avx2
        sp.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t]
        x = (np.random.default_rng(0).standard_normal((4096, 384)) * 3).astype(np.float32)
        y = np.empty_like(x)
        chain = graph([H.make_node("Relu", ["x"], ["r"]), H.make_node("Abs", ["x"], ["a"]),
                       H.make_node("Sigmoid", ["a"], ["s"]), H.make_node("Log", ["s"], ["l"]),
                       H.make_node("Sub", ["r", "l"], ["y"])], [V("x", TP.FLOAT, ["n", 384])], [V("y", TP.FLOAT, None)])
        ref = np.logaddexp(0.0, x.astype(np.float64))
        sp(x.ctypes.data, y.ctypes.data, x.size)
        runtime = Softplus()
        t_c = best(lambda: sp(x.ctypes.data, y.ctypes.data, x.size))
        t_np = best(lambda: runtime(x.copy()))
        t_copy = best(lambda: x.copy())
        t_ort = best(lambda: chain.run(None, {"x": x}))
        n = x.size
        rows.append(("softplus (4096 x 384)", f"onnxruntime chain {t_ort[0] / n * 1e9:.2f} ns/elem; runtime numpy + OpenCV "
                     f"{(t_np[0] - t_copy[0]) / n * 1e9:.2f} ns/elem", f"{t_c[0] / n * 1e9:.2f} ns/elem "
                     f"(max abs err {np.abs(y - ref).max():.1e})", f"{(t_np[0] - t_copy[0]) / t_c[0]:.1f}x vs the runtime"))
        f = df_lib.deform_sample
        P_, I_ = ctypes.c_void_p, ctypes.c_int
        f.argtypes = [P_, I_, I_, I_, I_, I_, I_, P_, P_, P_, P_]
        gs = graph([H.make_node("GridSample", ["v", "grid"], ["s"], align_corners=0, mode="bilinear", padding_mode="zeros"),
                    H.make_node("Mul", ["s", "w"], ["sw"]), H.make_node("ReduceSum", ["sw", "ax"], ["o"], keepdims=0)],
                   [V("v", TP.FLOAT, ["h", "c", "H", "W"]), V("grid", TP.FLOAT, ["h", "P", "Q", 2]), V("w", TP.FLOAT, ["h", 1, "P", "Q"])],
                   [V("o", TP.FLOAT, None)], [H.make_tensor(name="ax", data_type=TP.INT64, dims=[1], vals=[2])])
        rng = np.random.default_rng(0)
        for label, P, Q in (("image attention, plane_xy", 24, 2500), ("image attention, side plane", 96, 400),
                            ("cross-view attention, plane_xy", 12, 2500)):
            h, dh, Hc, Wc = 4, 16, 48, 276
            v = rng.standard_normal((h, dh, Hc, Wc)).astype(np.float32)
            grid = rng.uniform(-1.05, 1.05, (h, P, Q, 2)).astype(np.float32)
            w = rng.uniform(0, 1, (h, 1, P, Q)).astype(np.float32)
            canvas = np.ascontiguousarray(v.reshape(h * dh, Hc, Wc).transpose(1, 2, 0))
            gx, gy = np.ascontiguousarray(grid[..., 0]), np.ascontiguousarray(grid[..., 1])
            wc, out = np.ascontiguousarray(w[:, 0]), np.empty((h, dh, Q), np.float32)
            want = gs.run(None, {"v": v, "grid": grid, "w": w})[0]
            call = lambda: f(canvas.ctypes.data, Hc, Wc, h * dh, h, P, Q, gx.ctypes.data, gy.ctypes.data,  # noqa: E731
                             wc.ctypes.data, out.ctypes.data)
            call()
            t_o, t_k = best(lambda: gs.run(None, {"v": v, "grid": grid, "w": w})), best(call)
            rows.append((f"{label} ({P} points x {Q} queries)", f"onnxruntime {t_o[0] * 1e3:.2f} ms",
                         f"{t_k[0] * 1e3:.2f} ms (max abs diff {np.abs(out - want).max():.1e})", f"{t_o[0] / t_k[0]:.1f}x"))
    print(f"load average {load} -> {' '.join(f'{x:.2f}' for x in os.getloadavg())}; best of 15; "
          f"{os.environ['OMP_NUM_THREADS']} threads\n")
    print("| kernel | today | C prototype | gain |\n|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")


if __name__ == "__main__":
    main()
