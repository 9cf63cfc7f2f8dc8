"""Runtime speed: the torch-free runtime (onnxruntime encoder + numpy folded heads) vs torch eager.

Per frame, same weights and same inputs, in one run, for two model configs:
- "cpu": the default preset (100 x 100 x 8 grid, 352 x 192 images);
- "cpu@200x200x16": the same network on the Occ3D grid (TPV planes 100 x 100).
Weights are random (ago_export.testing.random_checkpoint): speed does not depend on training.

Measures: end-to-end per-frame time of both (from preprocessed tensors; preprocessing is shared and
reported once), the voxel head's GFLOP/s against this machine's float32 matmul ceiling (numpy sgemm,
measured here), bank swap time (a new prompt file -> bank encoded -> folded -> first prediction),
peak RSS of one prediction in a fresh subprocess (resource.getrusage), head cost vs grid size and vs
number of prompts, and numpy vs a small ORT graph for the head's reductions.

    python benchmarks/runtime_speed.py                  # writes benchmarks/results/runtime_speed.md
    python benchmarks/runtime_speed.py --configs cpu --reps 2
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("AGO_NO_PROGRESS", "1")

SHARED_SAMPLE = REPO.parent / "shared" / "data" / "nuscenes-sample"
RESULTS = REPO / "benchmarks" / "results" / "runtime_speed.md"
TARGETS = {"speedup_cpu": 1.5, "speedup_occ": 3.0, "head_ceiling": 0.5, "swap_s": 1.0, "rss_gib": 2.0}


def model_config(name: str):
    from ago_runtime.grid import Grid
    from ago_train.model import ModelConfig

    cfg = ModelConfig.preset("cpu")
    cfg.pretrained = False
    if name == "cpu@200x200x16":
        cfg.grid = Grid.occ3d().to_dict()
        cfg.tpv_h, cfg.tpv_w = 100, 100
    return cfg


def load_frame(rig_default):
    """The real nuScenes keyframe when present, else the exporter's synthetic frame."""
    if (SHARED_SAMPLE / "mmdet3d_info.pkl").is_file():
        from ago_runtime.mmdet3d_info import load_mmdet3d_info

        f = load_mmdet3d_info(SHARED_SAMPLE / "mmdet3d_info.pkl", SHARED_SAMPLE)[0]
        return f.images, f.rig, f"nuScenes {f.token} (1600x900)"
    from ago_export.export import synthetic_frame

    return synthetic_frame(rig_default)


def median_time(fn, reps: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(reps):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def matmul_ceiling() -> float:
    """Best float32 GFLOP/s of numpy sgemm over a few large square sizes."""
    best = 0.0
    rng = np.random.default_rng(0)
    for n in (1024, 2048, 3072):
        a = rng.standard_normal((n, n), dtype=np.float32)
        a @ a
        t, _ = median_time(lambda: a @ a, 3)
        best = max(best, 2 * n ** 3 / t / 1e9)
    return best


def torch_predict(model, x, m, T, groups):
    """Torch eager: forward + class max + softmax + entropy + min-entropy identifier + argmax."""
    import torch

    with torch.no_grad():
        out = model(x, m)
        res = []
        for f in (out["feat"][0], out["feat_adapted"][0]):
            s = f @ T.T
            z = torch.stack([s[:, a:b].amax(1) for a, b in groups] + [s[:, -1]], 1)
            logp = torch.log_softmax(z, 1)
            ent = -(logp.exp() * logp).sum(1)
            res.append((z.argmax(1), ent))
        (lm, em), (la, ea) = res
        return torch.where(ea < em, la, lm)


def ort_head_graph(K1: int, G: int, D: int) -> bytes:
    """One branch of the head as an ONNX graph: Gemm -> reshape (K1, G, n) -> max -> log-softmax stats."""
    import onnx
    from onnx import TensorProto as TP
    from onnx import helper as H

    nodes = [H.make_node("Gemm", ["A", "x", "c"], ["s"], transB=1),
             H.make_node("Reshape", ["s", "shp"], ["s3"]),
             H.make_node("ReduceMax", ["s3", "ax1"], ["z"], keepdims=0),
             H.make_node("LogSoftmax", ["z"], ["lp"], axis=0), H.make_node("Exp", ["lp"], ["p"]),
             H.make_node("Mul", ["p", "lp"], ["plp"]), H.make_node("ReduceSum", ["plp", "ax0"], ["nh"], keepdims=0),
             H.make_node("Neg", ["nh"], ["ent"]), H.make_node("ArgMax", ["z"], ["label"], axis=0, keepdims=0),
             H.make_node("ReduceMax", ["p", "ax0"], ["conf"], keepdims=0)]
    inits = [H.make_tensor("shp", TP.INT64, [3], [K1, G, -1]), H.make_tensor("ax1", TP.INT64, [1], [1]),
             H.make_tensor("ax0", TP.INT64, [1], [0])]
    g = H.make_graph(nodes, "head", [H.make_tensor_value_info("A", TP.FLOAT, ["R", D]),
                                     H.make_tensor_value_info("x", TP.FLOAT, ["n", D]),
                                     H.make_tensor_value_info("c", TP.FLOAT, ["R", 1])],
                     [H.make_tensor_value_info("label", TP.INT64, ["n"]),
                      H.make_tensor_value_info("ent", TP.FLOAT, ["n"]),
                      H.make_tensor_value_info("conf", TP.FLOAT, ["n"])], inits)
    model = H.make_model(g, opset_imports=[H.make_opsetid("", 18)], ir_version=9)
    onnx.checker.check_model(model)
    return model.SerializeToString()


def numpy_vs_ort_heads(N: int, D: int, K: int, G: int, reps: int, chunk: int = 65536) -> dict:
    """One branch, K classes x G phrases each (+ free padded to G): numpy FoldedHeads vs the ORT graph."""
    import onnxruntime as ort

    from ago_runtime.heads import FoldedHeads, HeadWeights

    rng = np.random.default_rng(0)
    C = 384
    w = HeadWeights(*(rng.standard_normal(s).astype(np.float32) * 0.1 for s in ((C, D), (C,), (C, D), (C,), (C,))))
    pc = np.repeat(np.arange(K), G)
    emb = rng.standard_normal((len(pc), C)).astype(np.float32)
    fh = FoldedHeads(w, emb, pc, K)
    x = rng.standard_normal((N, D)).astype(np.float32)
    t_np, _ = median_time(lambda: fh.run(x, x, "none", chunk), reps)
    # ORT: rows padded to (K + 1) x G by repeating the free row
    A = np.concatenate([fh.A_main_T, np.repeat(fh.A_main_T[-1:], G - 1, 0)])
    c = np.concatenate([fh.c_main, np.repeat(fh.c_main[-1:], G - 1, 0)])
    so = ort.SessionOptions()
    sess = ort.InferenceSession(ort_head_graph(K + 1, G, D), so, providers=["CPUExecutionProvider"])

    def run_ort():
        for s in range(0, N, chunk):
            sess.run(None, {"A": A, "x": x[s:s + chunk], "c": c})

    t_ort, _ = median_time(run_ort, reps)
    lab_np = fh.run(x[:chunk], x[:chunk], "none")["label"]
    lab_ort = sess.run(None, {"A": A, "x": x[:chunk], "c": c})[0]
    return {"N": N, "numpy_s": t_np, "ort_s": t_ort, "agree": float(np.mean(lab_np == lab_ort))}


def rss_child(kind: str, bundle: str, ckpt: str) -> None:
    """Run one prediction and print peak RSS (MiB) as JSON."""
    rig_images = None
    if kind == "runtime":
        from ago_runtime.predictor import Predictor

        p = Predictor(bundle)
        images, rig, _ = load_frame(p.bundle.rig)
        p.predict(images, rig)
        rig_images = "ok"
    else:
        import torch

        from ago_export.export import load_model
        from ago_runtime.bundle import Bundle

        b = Bundle.load(bundle)
        model, _, cfg = load_model(ckpt)
        images, rig, _ = load_frame(b.rig)
        x = torch.from_numpy(b.preprocess.images(images)[None])
        m = torch.from_numpy(b.preprocess.ego2img(rig)[None])
        bank = b.load_bank()
        order = np.argsort(bank.phrase_class, kind="stable")
        T = torch.from_numpy(np.concatenate([bank.embeddings[order], b.heads.free_embedding[None]]))
        starts = np.searchsorted(bank.phrase_class[order], np.arange(bank.num_classes + 1))
        groups = list(zip(starts[:-1].tolist(), starts[1:].tolist()))
        torch_predict(model, x, m, T, groups)
        rig_images = "ok"
    print(json.dumps({"kind": kind, "peak_rss_mib": peak_rss_mib(), "status": rig_images}))


def peak_rss_mib() -> float:
    """Peak RSS of this process's address space: VmHWM from /proc/self/status.

    resource.getrusage(RUSAGE_SELF).ru_maxrss is not usable in a child started by this (large)
    process: Linux carries ru_maxrss over fork + exec, so the child would report the parent's peak.
    Elsewhere (no /proc) fall back to ru_maxrss.
    """
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def peak_rss(kind: str, bundle: Path, ckpt: Path) -> float:
    r = subprocess.run([sys.executable, __file__, "--rss-child", kind, str(bundle), str(ckpt)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(r.stderr[-2000:])
    return json.loads(r.stdout.strip().splitlines()[-1])["peak_rss_mib"]


def bench_config(name: str, work: Path, reps: int, ceiling: float) -> dict:
    import torch

    from ago_export.export import export_bundle, load_model
    from ago_export.testing import random_checkpoint
    from ago_runtime.bank import bank_for_prompts
    from ago_runtime.predictor import Predictor

    cfg = model_config(name)
    ckpt = random_checkpoint(work / f"{name}.pt", cfg, prompts="cw", seed=0)
    bundle = work / f"{name}_bundle"
    t = time.perf_counter()
    export_bundle(ckpt, bundle, bank_prompts=[], real_frame=False, parity=False, log=lambda s: None)
    export_s = time.perf_counter() - t
    model, _, _ = load_model(ckpt)
    pred = Predictor(bundle)
    bank = pred.bundle.load_bank()
    images, rig, frame_name = load_frame(pred.bundle.rig)
    t_pre, (x, m) = median_time(lambda: pred.prepare(images, rig), reps)
    # --- runtime
    folded = pred.fold(bank)
    pred.encode_arrays(x, m)   # warm-up
    t_enc, (h, g) = median_time(lambda: pred.encode_arrays(x, m), reps)
    pred.predict_hidden(h, g, bank, "min-entropy", folded)
    t_head, p = median_time(lambda: pred.predict_hidden(h, g, bank, "min-entropy", folded), reps)
    # --- torch eager, same weights and inputs
    order = np.argsort(bank.phrase_class, kind="stable")
    T = torch.from_numpy(np.concatenate([bank.embeddings[order], pred.bundle.heads.free_embedding[None]]))
    starts = np.searchsorted(bank.phrase_class[order], np.arange(bank.num_classes + 1))
    groups = list(zip(starts[:-1].tolist(), starts[1:].tolist()))
    xt, mt = torch.from_numpy(x), torch.from_numpy(m)
    torch_predict(model, xt, mt, T, groups)   # warm-up
    t_torch, lab_t = median_time(lambda: torch_predict(model, xt, mt, T, groups), reps)
    agree = float(np.mean(lab_t.numpy().reshape(-1) == p.semantics.reshape(-1)))
    N = pred.grid.num_voxels
    head_gflops = folded.flops_per_voxel("min-entropy") * N / t_head / 1e9
    # --- bank swap: a prompt file never seen before (unique text -> cache miss)
    prompt = work / f"swap_{name}.txt"
    prompt.write_text(f"# {time.time_ns()}\nfire hydrant: fire hydrant, hydrant\nmailbox: mailbox, letter box\n"
                      "road [driveable_surface]: road, street\nbuilding [manmade]: building, wall\n"
                      "tree [vegetation]: tree, bush\ncar: car, van\n")
    from ago_runtime.text_encoder import default_text_encoder

    t0 = time.perf_counter()
    new_bank = bank_for_prompts(prompt, cache_dir=work / "banks")   # cold: creates the text encoder session
    t1 = time.perf_counter()
    pred.fold(new_bank)
    t2 = time.perf_counter()
    pred.predict_hidden(h, g, new_bank)
    t3 = time.perf_counter()
    encoder = default_text_encoder()                                # warm: a long-lived process keeps it
    prompt.write_text(prompt.read_text().replace("# ", "# again "))
    t4 = time.perf_counter()
    warm_bank = bank_for_prompts(prompt, encoder=encoder, cache_dir=work / "banks")
    pred.fold(warm_bank)
    pred.predict_hidden(h, g, warm_bank)
    t5 = time.perf_counter()
    swap = {"encode_s": t1 - t0, "fold_s": t2 - t1, "heads_s": t3 - t2, "total_s": t3 - t0, "warm_total_s": t5 - t4}
    rss_rt = peak_rss("runtime", bundle, ckpt)
    rss_torch = peak_rss("torch", bundle, ckpt)
    return {"name": name, "grid": list(pred.grid.shape), "N": N, "frame": frame_name, "export_s": export_s,
            "preprocess_s": t_pre, "encoder_s": t_enc, "heads_s": t_head, "runtime_s": t_enc + t_head,
            "torch_s": t_torch, "speedup": t_torch / (t_enc + t_head), "agreement": agree,
            "head_gflops": head_gflops, "head_share_of_ceiling": head_gflops / ceiling,
            "hidden_dim": int(h.shape[1]), "adapter_dim": int(g.shape[1]), "phrases": int(bank.num_phrases),
            "swap": swap, "rss_runtime_mib": rss_rt, "rss_torch_mib": rss_torch}


def heads_scaling(reps: int, D_h: int, D_a: int, ceiling: float) -> tuple[list, list]:
    from ago_runtime.heads import FoldedHeads, HeadWeights

    rng = np.random.default_rng(0)
    C = 384
    w = HeadWeights(rng.standard_normal((C, D_h)).astype(np.float32), rng.standard_normal(C).astype(np.float32),
                    rng.standard_normal((C, D_a)).astype(np.float32), rng.standard_normal(C).astype(np.float32),
                    rng.standard_normal(C).astype(np.float32))
    grid_rows, prompt_rows = [], []
    K = 17
    pc = np.concatenate([np.arange(K), rng.integers(0, K, 17)])
    emb = rng.standard_normal((len(pc), C)).astype(np.float32)
    fh = FoldedHeads(w, emb, pc, K)
    for shape in ((50, 50, 4), (100, 100, 8), (200, 200, 16)):
        N = int(np.prod(shape))
        h = rng.standard_normal((N, D_h)).astype(np.float32)
        g = rng.standard_normal((N, D_a)).astype(np.float32)
        t, _ = median_time(lambda: fh.run(h, g), reps)
        grid_rows.append({"shape": shape, "N": N, "s": t, "ms_per_Mvox": t / N * 1e9,
                          "gflops": fh.flops_per_voxel() * N / t / 1e9})
    N = 100 * 100 * 8
    h = rng.standard_normal((N, D_h)).astype(np.float32)
    g = rng.standard_normal((N, D_a)).astype(np.float32)
    for P in (17, 68, 272, 1088):
        pc = np.concatenate([np.arange(K), rng.integers(0, K, P - K)])
        emb = rng.standard_normal((P, C)).astype(np.float32)
        fhp = FoldedHeads(w, emb, pc, K)
        t, _ = median_time(lambda: fhp.run(h, g), reps)
        gf = fhp.flops_per_voxel() * N / t / 1e9
        prompt_rows.append({"P": P, "s": t, "gflops": gf, "share": gf / ceiling})
    return grid_rows, prompt_rows


def write_report(res: dict, path: Path) -> str:
    L = []
    L.append("# Runtime speed: onnxruntime + numpy vs torch eager\n")
    L.append(f"Command: `{res['command']}`  \nMachine: {res['machine']}; load average at start {res['load_start']}, "
             f"at end {res['load_end']} (other jobs shared these {os.cpu_count()} cores: timings are noisy).  \n"
             f"Threads: onnxruntime default (= cores), torch {res['torch_threads']}, numpy/OpenBLAS default.  \n"
             f"Weights: random (same weights for both paths); label space cw (17 classes); frame: {res['frame']}.  \n"
             f"float32 matmul ceiling (numpy sgemm, best of 1024/2048/3072 square): **{res['ceiling']:.1f} GFLOP/s**.\n")
    L.append("## Per frame (median of %d runs, from preprocessed tensors)\n" % res["reps"])
    L.append("| config | grid | torch eager s | runtime s (encoder + heads) | speedup (target) | heads GFLOP/s (share of ceiling) | argmax agreement | preprocess s |")
    L.append("|---|---|---|---|---|---|---|---|")
    for c in res["configs"]:
        tgt = TARGETS["speedup_occ"] if "200" in c["name"] else TARGETS["speedup_cpu"]
        L.append(f"| {c['name']} | {'x'.join(map(str, c['grid']))} | {c['torch_s']:.2f} | {c['runtime_s']:.2f} "
                 f"({c['encoder_s']:.2f} + {c['heads_s']:.3f}) | **{c['speedup']:.2f}x** (>= {tgt}x: "
                 f"{'met' if c['speedup'] >= tgt else 'MISSED'}) | {c['head_gflops']:.1f} ({c['head_share_of_ceiling']:.0%}; "
                 f"target 50%: {'met' if c['head_share_of_ceiling'] >= 0.5 else 'MISSED'}) | {c['agreement']:.4f} | "
                 f"{c['preprocess_s']:.3f} |")
    L.append("\n## Bank swap (new prompt file -> encoded -> folded -> first heads result) and peak RSS\n")
    L.append("| config | encode prompts s | fold s | heads s | swap total s, cold (target < 1 s) | swap total s, text encoder loaded | peak RSS runtime MiB (target < 2048) | peak RSS torch MiB |")
    L.append("|---|---|---|---|---|---|---|---|")
    for c in res["configs"]:
        s = c["swap"]
        L.append(f"| {c['name']} | {s['encode_s']:.3f} | {s['fold_s']:.4f} | {s['heads_s']:.3f} | **{s['total_s']:.3f}** "
                 f"({'met' if s['total_s'] < 1 else 'MISSED'}) | {s['warm_total_s']:.3f} | **{c['rss_runtime_mib']:.0f}** "
                 f"({'met' if c['rss_runtime_mib'] < 2048 else 'MISSED'}) | {c['rss_torch_mib']:.0f} |")
    L.append("\nCold swap: bank_for_prompts creates the text encoder's onnxruntime session, encodes the phrases, "
             "caches the bank; then fold + heads. Warm: the text encoder is already loaded (a long-lived process). "
             "Both reuse the frame's encoder features (a new frame adds one encoder run). Peak RSS: VmHWM of a "
             "fresh subprocess doing one prediction (load bundle/model, read the frame, predict).\n")
    L.append(f"## Head cost vs grid size (numpy folded heads, both branches + identifier; Dh={res['Dh']}, Da={res['Da']}, 34 phrases)\n")
    L.append("| grid | voxels | s | ms per million voxels | GFLOP/s |")
    L.append("|---|---|---|---|---|")
    for r in res["grid_rows"]:
        L.append(f"| {'x'.join(map(str, r['shape']))} | {r['N']} | {r['s']:.3f} | {r['ms_per_Mvox']:.0f} | {r['gflops']:.1f} |")
    L.append("\n## Head cost vs number of prompts (100x100x8, 17 classes)\n")
    L.append("| phrases | s | GFLOP/s | share of ceiling |")
    L.append("|---|---|---|---|")
    for r in res["prompt_rows"]:
        L.append(f"| {r['P']} | {r['s']:.3f} | {r['gflops']:.1f} | {r['share']:.0%} |")
    L.append("\n## Head reductions: numpy vs a small ORT graph (one branch, 18 classes x 4 phrases, D=128)\n")
    L.append("| voxels | numpy s | ORT graph s | numpy / ORT | label agreement |")
    L.append("|---|---|---|---|---|")
    for r in res["np_vs_ort"]:
        L.append(f"| {r['N']} | {r['numpy_s']:.3f} | {r['ort_s']:.3f} | {r['numpy_s'] / r['ort_s']:.2f} | {r['agree']:.4f} |")
    L.append("\nThe runtime uses the numpy path (see docs/runtime.md, 'Head implementation').\n")
    text = "\n".join(L) + "\n"
    from ago_runtime.atomic import write_text

    write_text(path, text)
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--configs", default="cpu,cpu@200x200x16")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--rss-child", nargs=3, metavar=("KIND", "BUNDLE", "CKPT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.rss_child:
        rss_child(*args.rss_child)
        return
    import torch

    load_start = " ".join(f"{x:.1f}" for x in os.getloadavg())
    ceiling = matmul_ceiling()
    print(f"matmul ceiling {ceiling:.1f} GFLOP/s", flush=True)
    with tempfile.TemporaryDirectory(prefix="ago_bench_") as tmp:
        os.environ["AGO_CACHE_DIR"] = str(Path(tmp) / "cache")
        configs = []
        for name in args.configs.split(","):
            c = bench_config(name, Path(tmp), args.reps, ceiling)
            print(json.dumps(c), flush=True)
            configs.append(c)
    grid_rows, prompt_rows = heads_scaling(args.reps, configs[0]["hidden_dim"], configs[0]["adapter_dim"], ceiling)
    np_vs_ort = [numpy_vs_ort_heads(N, 128, 17, 4, args.reps) for N in (80000, 640000)]
    cpu = platform.processor() or platform.machine()
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    res = {"command": "python " + " ".join([Path(sys.argv[0]).as_posix()] + sys.argv[1:]),
           "machine": f"{cpu}, {os.cpu_count()} cores", "load_start": load_start,
           "load_end": " ".join(f"{x:.1f}" for x in os.getloadavg()), "torch_threads": torch.get_num_threads(),
           "frame": configs[0]["frame"], "ceiling": ceiling, "reps": args.reps, "configs": configs,
           "grid_rows": grid_rows, "prompt_rows": prompt_rows, "np_vs_ort": np_vs_ort,
           "Dh": configs[0]["hidden_dim"], "Da": configs[0]["adapter_dim"]}
    print(write_report(res, args.out))


if __name__ == "__main__":
    main()
