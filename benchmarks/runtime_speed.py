"""Runtime speed: the torch-free runtime (onnxruntime encoder + numpy folded heads) vs torch eager.

Per frame, same weights and same inputs, in one run, for two model configs:
- "cpu": the default preset (100 x 100 x 8 grid, 352 x 192 images);
- "cpu@200x200x16": the same network on the Occ3D grid (TPV planes 100 x 100).
Weights are random (ago_export.testing.random_checkpoint): speed does not depend on training.

Measures: end-to-end per-frame time of both (from preprocessed tensors; preprocessing is shared and
reported once), the voxel head's GFLOP/s against this machine's float32 matmul ceiling (numpy sgemm,
measured here), bank swap time (a new prompt file -> bank encoded -> folded -> first prediction),
peak RSS of one prediction in a fresh subprocess (resource.getrusage), head cost vs grid size and vs
number of prompts (the runtime heads, and for reference the numpy-only heads: FoldedHeads.run).

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


def matmul_ceiling() -> dict:
    """Best float32 GFLOP/s over a few large square sizes: numpy sgemm (OpenBLAS) and onnxruntime MatMul (MLAS)."""
    import onnxruntime as ort

    best = {"numpy": 0.0, "onnxruntime": 0.0}
    rng = np.random.default_rng(0)
    sess = ort.InferenceSession(gemm_graph(trans_b=False), providers=["CPUExecutionProvider"])
    for n in (1024, 2048, 3072):
        a = rng.standard_normal((n, n), dtype=np.float32)
        for kind, fn in (("numpy", lambda: a @ a), ("onnxruntime", lambda: sess.run(None, {"A": a, "x": a}))):
            fn()
            t, _ = median_time(fn, 3)
            best[kind] = max(best[kind], 2 * n ** 3 / t / 1e9)
    best["best"] = max(best["numpy"], best["onnxruntime"])
    return best


def gemm_graph(trans_b: bool = True) -> bytes:
    """Y = A @ x^T (trans_b) or A @ x: the heads' product as voxels.onnx does it, alone (benchmarks only)."""
    from onnx import TensorProto as TP
    from onnx import helper as H

    node = H.make_node("Gemm", ["A", "x"], ["y"], transB=1) if trans_b else H.make_node("MatMul", ["A", "x"], ["y"])
    g = H.make_graph([node], "gemm", [H.make_tensor_value_info("A", TP.FLOAT, ["R", "D"]),
                                      H.make_tensor_value_info("x", TP.FLOAT, ["n", "D"] if trans_b else ["D", "n"])],
                     [H.make_tensor_value_info("y", TP.FLOAT, ["R", "n"])])
    return H.make_model(g, opset_imports=[H.make_opsetid("", 17)], ir_version=9).SerializeToString()


class RuntimeHeads:
    """The runtime's heads on given h, g: the bank's GEMM in onnxruntime (as inside voxels.onnx), then the
    numpy class max / softmax / identifier (FoldedHeads.classify_scores), in 65 536-voxel chunks."""

    def __init__(self):
        from ago_runtime.encoder import session_options

        import onnxruntime as ort

        self.sess = ort.InferenceSession(gemm_graph(), session_options(), providers=["CPUExecutionProvider"])

    def run(self, fh, h, g, identifier="min-entropy", chunk=65536):
        label = np.empty(h.shape[0], np.intp)
        for s in range(0, h.shape[0], chunk):
            s_main = self.sess.run(None, {"A": fh.A_main_T, "x": h[s:s + chunk]})[0]
            s_ad = self.sess.run(None, {"A": fh.A_ad_T, "x": g[s:s + chunk]})[0] if identifier != "none" else None
            label[s:s + chunk] = fh.classify_scores(s_main, s_ad, identifier)[0]
        return label


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
    pred.predict_arrays(x, m, bank, "min-entropy", folded)   # warm-up
    # what `ago infer` does per frame: planes once, then slab by slab voxel MLPs -> heads (streamed)
    t_rt, p = median_time(lambda: pred.predict_arrays(x, m, bank, "min-entropy", folded), reps)
    t_enc, t_head_streamed = p.timings["encoder"], p.timings["heads"]
    # the heads alone on the whole grid's features (their GFLOP/s): the runtime's (ORT GEMM + numpy)
    # and the numpy-only one (FoldedHeads.run, its GEMM in OpenBLAS) for reference
    h, g = pred.encode_arrays(x, m)
    rh = RuntimeHeads()
    rh.run(folded, h, g)
    t_head, _ = median_time(lambda: rh.run(folded, h, g), reps)
    pred.predict_hidden(h, g, bank, "min-entropy", folded)
    t_head_np, _ = median_time(lambda: pred.predict_hidden(h, g, bank, "min-entropy", folded), reps)
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
    head_gflops_np = folded.flops_per_voxel("min-entropy") * N / t_head_np / 1e9
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
    pred.predict_arrays(x, m, new_bank)     # the first prediction with the new bank (whole frame)
    t3 = time.perf_counter()
    encoder = default_text_encoder()                                # warm: a long-lived process keeps it
    prompt.write_text(prompt.read_text().replace("# ", "# again "))
    t4 = time.perf_counter()
    warm_bank = bank_for_prompts(prompt, encoder=encoder, cache_dir=work / "banks")
    pred.fold(warm_bank)
    t45 = time.perf_counter()
    pred.predict_arrays(x, m, warm_bank)
    t5 = time.perf_counter()
    swap = {"encode_s": t1 - t0, "fold_s": t2 - t1, "heads_s": t3 - t2, "total_s": t3 - t0, "warm_total_s": t5 - t4,
            "overhead_s": t2 - t0, "warm_overhead_s": t45 - t4}
    rss_rt = peak_rss("runtime", bundle, ckpt)
    rss_torch = peak_rss("torch", bundle, ckpt)
    return {"name": name, "grid": list(pred.grid.shape), "N": N, "frame": frame_name, "export_s": export_s,
            "preprocess_s": t_pre, "encoder_s": t_enc, "heads_s": t_head_streamed, "heads_alone_s": t_head,
            "runtime_s": t_rt, "torch_s": t_torch, "speedup": t_torch / t_rt, "agreement": agree,
            "head_gflops": head_gflops, "head_share_of_ceiling": head_gflops / ceiling,
            "heads_numpy_s": t_head_np, "head_gflops_numpy": head_gflops_np,
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
    rh = RuntimeHeads()
    K = 17
    pc = np.concatenate([np.arange(K), rng.integers(0, K, 17)])
    emb = rng.standard_normal((len(pc), C)).astype(np.float32)
    fh = FoldedHeads(w, emb, pc, K)
    for shape in ((50, 50, 4), (100, 100, 8), (200, 200, 16)):
        N = int(np.prod(shape))
        h = rng.standard_normal((N, D_h)).astype(np.float32)
        g = rng.standard_normal((N, D_a)).astype(np.float32)
        rh.run(fh, h, g)
        t, _ = median_time(lambda: rh.run(fh, h, g), reps)
        t_np, _ = median_time(lambda: fh.run(h, g), reps)
        grid_rows.append({"shape": shape, "N": N, "s": t, "ms_per_Mvox": t / N * 1e9,
                          "gflops": fh.flops_per_voxel() * N / t / 1e9, "s_numpy": t_np,
                          "gflops_numpy": fh.flops_per_voxel() * N / t_np / 1e9})
    N = 100 * 100 * 8
    h = rng.standard_normal((N, D_h)).astype(np.float32)
    g = rng.standard_normal((N, D_a)).astype(np.float32)
    for P in (17, 68, 272, 1088):
        pc = np.concatenate([np.arange(K), rng.integers(0, K, P - K)])
        emb = rng.standard_normal((P, C)).astype(np.float32)
        fhp = FoldedHeads(w, emb, pc, K)
        rh.run(fhp, h, g)
        t, _ = median_time(lambda: rh.run(fhp, h, g), reps)
        t_np, _ = median_time(lambda: fhp.run(h, g), reps)
        gf = fhp.flops_per_voxel() * N / t / 1e9
        prompt_rows.append({"P": P, "s": t, "gflops": gf, "share": gf / ceiling, "s_numpy": t_np,
                            "gflops_numpy": fhp.flops_per_voxel() * N / t_np / 1e9})
    return grid_rows, prompt_rows


def write_report(res: dict, path: Path) -> str:
    L = []
    L.append("# Runtime speed: onnxruntime + numpy vs torch eager\n")
    L.append(f"Command: `{res['command']}`  \nMachine: {res['machine']}; load average at start {res['load_start']}, "
             f"at end {res['load_end']} (other jobs shared these {os.cpu_count()} cores: timings are noisy).  \n"
             f"Threads: onnxruntime default (= cores), torch {res['torch_threads']}, numpy/OpenBLAS default.  \n"
             f"Weights: random (same weights for both paths); label space cw (17 classes); frame: {res['frame']}.  \n"
             f"float32 matmul ceiling (best of 1024/2048/3072 square): numpy sgemm {res['ceilings']['numpy']:.1f}, "
             f"onnxruntime MatMul {res['ceilings']['onnxruntime']:.1f}: **{res['ceiling']:.1f} GFLOP/s**.  \n"
             "Runtime = bundle format 2 (planes.onnx once, voxels.onnx per slab of 65 536 voxels with the bank's "
             "GEMM inside, numpy class max / softmax / identifier; ago_runtime/encoder.py).\n")
    L.append("## Per frame (median of %d runs, from preprocessed tensors)\n" % res["reps"])
    L.append("| config | grid | torch eager s | runtime s (graphs + numpy heads, streamed per slab) | speedup (target) | heads alone s; GFLOP/s (share of ceiling) | heads numpy-only s; GFLOP/s | argmax agreement | preprocess s |")
    L.append("|---|---|---|---|---|---|---|---|---|")
    for c in res["configs"]:
        tgt = TARGETS["speedup_occ"] if "200" in c["name"] else TARGETS["speedup_cpu"]
        L.append(f"| {c['name']} | {'x'.join(map(str, c['grid']))} | {c['torch_s']:.2f} | {c['runtime_s']:.2f} "
                 f"({c['encoder_s']:.2f} + {c['heads_s']:.3f}) | **{c['speedup']:.2f}x** (>= {tgt}x: "
                 f"{'met' if c['speedup'] >= tgt else 'MISSED'}) | {c['heads_alone_s']:.3f}; {c['head_gflops']:.1f} ({c['head_share_of_ceiling']:.0%}; "
                 f"target 50%: {'met' if c['head_share_of_ceiling'] >= 0.5 else 'MISSED'}) | {c['heads_numpy_s']:.3f}; "
                 f"{c['head_gflops_numpy']:.1f} | {c['agreement']:.4f} | "
                 f"{c['preprocess_s']:.3f} |")
    L.append("\n## Bank swap (new prompt file -> encoded -> folded -> first heads result) and peak RSS\n")
    L.append("| config | encode prompts s | fold s | first prediction s | swap total s, cold (target < 1 s) | swap overhead s (encode + fold) | swap total s, text encoder loaded | peak RSS runtime MiB (target < 2048) | peak RSS torch MiB |")
    L.append("|---|---|---|---|---|---|---|---|---|")
    for c in res["configs"]:
        s = c["swap"]
        L.append(f"| {c['name']} | {s['encode_s']:.3f} | {s['fold_s']:.4f} | {s['heads_s']:.3f} | **{s['total_s']:.3f}** "
                 f"({'met' if s['total_s'] < 1 else 'MISSED'}) | {s['overhead_s']:.3f} | {s['warm_total_s']:.3f} | "
                 f"**{c['rss_runtime_mib']:.0f}** ({'met' if c['rss_runtime_mib'] < 2048 else 'MISSED'}) | "
                 f"{c['rss_torch_mib']:.0f} |")
    L.append("\nCold swap: bank_for_prompts creates the text encoder's onnxruntime session, encodes the phrases, "
             "caches the bank; then fold; then the first prediction of the whole frame with the new bank (the bank's "
             "product runs inside voxels.onnx, so this is a full frame: the swap itself costs only encode + fold). "
             "Warm: the text encoder is already loaded (a long-lived process). Peak RSS: VmHWM of a "
             "fresh subprocess doing one prediction (load bundle/model, read the frame, predict).\n")
    L.append(f"## Head cost vs grid size (both branches + identifier; Dh={res['Dh']}, Da={res['Da']}, 34 phrases)\n")
    L.append("Runtime heads = bank GEMM in onnxruntime + numpy reductions; numpy-only = the same heads with numpy's GEMM (FoldedHeads.run), for reference.\n")
    L.append("| grid | voxels | runtime s | ms per million voxels | GFLOP/s (share of ceiling) | numpy-only s | numpy-only GFLOP/s |")
    L.append("|---|---|---|---|---|---|---|")
    for r in res["grid_rows"]:
        L.append(f"| {'x'.join(map(str, r['shape']))} | {r['N']} | {r['s']:.3f} | {r['ms_per_Mvox']:.0f} | "
                 f"{r['gflops']:.1f} ({r['gflops'] / res['ceiling']:.0%}) | {r['s_numpy']:.3f} | {r['gflops_numpy']:.1f} |")
    L.append("\n## Head cost vs number of prompts (100x100x8, 17 classes)\n")
    L.append("| phrases | runtime s | GFLOP/s | share of ceiling | numpy-only s | numpy-only GFLOP/s |")
    L.append("|---|---|---|---|---|---|")
    for r in res["prompt_rows"]:
        L.append(f"| {r['P']} | {r['s']:.3f} | {r['gflops']:.1f} | {r['share']:.0%} | {r['s_numpy']:.3f} | "
                 f"{r['gflops_numpy']:.1f} |")
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
    ceilings = matmul_ceiling()
    ceiling = ceilings["best"]
    print(f"matmul ceiling {ceilings}", flush=True)
    with tempfile.TemporaryDirectory(prefix="ago_bench_") as tmp:
        os.environ["AGO_CACHE_DIR"] = str(Path(tmp) / "cache")
        configs = []
        for name in args.configs.split(","):
            c = bench_config(name, Path(tmp), args.reps, ceiling)
            print(json.dumps(c), flush=True)
            configs.append(c)
    grid_rows, prompt_rows = heads_scaling(args.reps, configs[0]["hidden_dim"], configs[0]["adapter_dim"], ceiling)
    cpu = platform.processor() or platform.machine()
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    res = {"command": "python " + " ".join([Path(sys.argv[0]).as_posix()] + sys.argv[1:]),
           "machine": f"{cpu}, {os.cpu_count()} cores", "load_start": load_start,
           "load_end": " ".join(f"{x:.1f}" for x in os.getloadavg()), "torch_threads": torch.get_num_threads(),
           "frame": configs[0]["frame"], "ceiling": ceiling, "reps": args.reps, "configs": configs,
           "grid_rows": grid_rows, "prompt_rows": prompt_rows, "ceilings": ceilings,
           "Dh": configs[0]["hidden_dim"], "Da": configs[0]["adapter_dim"]}
    print(write_report(res, args.out))


if __name__ == "__main__":
    main()
