"""Runtime speed: this tree's runtime (bundle format 3) against the baseline's (commit 073a3f4, bundle
format 2), side by side in one run, with the FLOP bound of this CPU.

The baseline code is extracted from git (`git archive 073a3f4`) into a temp folder and run in
subprocesses with PYTHONPATH pointing there; this tree's code runs in subprocesses with PYTHONPATH
pointing here. Every measurement is a fresh child process; baseline and new children alternate, and
each figure is the best (minimum) of the rounds' medians, so a load spike on this shared machine
hits both sides alike.

Configs:
- "cpu": the default preset (100 x 100 x 8 grid, 352 x 192 images). Baseline bundle: the shipped
  format-2 default bundle of the baseline tree (`--baseline export`: the baseline code's export of
  the random checkpoint instead). New bundle: this tree's shipped bundle when it is format 3 at this
  grid, else this tree's export of `--ckpt-cpu` (a trained checkpoint, on its model grid), else of a
  random checkpoint of the preset (the export runs the parity check against torch on the real nuScenes
  frame). When the shipped bundle reads out on another grid (200x200x16), it is timed on its own
  (new side only: frame, first frame, RSS, `ago infer`).
- "cpu@200x200x16": the same network on the Occ3D grid (TPV planes 100 x 100); the baseline exports a
  random checkpoint (format 2 runs every branch on every voxel: its time does not depend on the weights);
  the new side exports the checkpoint of `--ckpt-200` (a model trained on that grid:
  `bash benchmarks/make_model_200.sh`), else a random checkpoint, whose ~100 % occupied voxels are the new
  runtime's worst case (it runs the adapted branch on the occupied voxels only).

Per config and side: steady-state frame (median of --reps predictions from preprocessed tensors;
planes graph alone, graphs + heads), the first frame of a new process (the first prediction after
`Predictor(bundle)`; the open time is reported too), peak RSS (VmHWM of the child), bank swap (a new
prompt file -> encoded (new text encoder session) -> folded -> first prediction with it), for this tree
also the re-query of the same frame with another new prompt file and the frame's planes passed in
(`predict_arrays(..., features=FrameFeatures)`: planes and every voxel's h kept; the baseline cannot), the
steady state with the bundle's default identifier for its training bank (what `ago infer` runs: `none` for a
closed-world bank in this tree), and the share of voxels the main branch calls occupied (the new
runtime runs the adapted branch on those only). The children pick their tree's module paths by its
layout (`tree_module`: the baseline has the flat ago_runtime of before the reorganisation). For "cpu" also
`ago infer --images DATASET` over a 12-frame synthetic dataset (run_infer in a child: bundle load,
decode, encoder, heads, npz and PNG written), per frame.

FLOP bound: matmul + conv FLOPs of one frame (torch.utils.flop_counter on the torch modules that are
exported: today's model forward + the bank's product, and this tree's PlanesGraph + VoxelsGraph) /
this CPU's best measured fp32 rate (onnxruntime MatMul at 1024..3072 and a 3x3 Conv).

    python -m benchmarks.runtime_speed --ckpt-200 work/s6/train200/last.pt --ckpt-cpu work/db24/train/last.pt
        # writes benchmarks/results/runtime_speed.md
    python -m benchmarks.runtime_speed --configs cpu --reps 5 --rounds 2
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BASELINE_COMMIT = "073a3f4"
SHARED_SAMPLE = REPO.parent / "shared" / "data" / "nuscenes-sample"
RESULTS = REPO / "benchmarks" / "results" / "runtime_speed.md"
REFERENCE_RATE = 300.0   # GFLOP/s: the best measured fp32 rate here on a quiet machine (3x3 Conv)
TARGETS = {"speedup": 2.0, "bound_share": 0.30, "first_ratio": 1.5, "swap_s": 1.0,
           "rss_mib": {"cpu": 800, "cpu@200x200x16": 1536}, "infer_speedup": 2.0, "infer_vs_steady": 1.3}
SWAP_PROMPTS = ("fire hydrant: fire hydrant, hydrant\nmailbox: mailbox, letter box\n"
                "road [driveable_surface]: road, street\nbuilding [manmade]: building, wall\n"
                "tree [vegetation]: tree, bush\ncar: car, van\n")


# ---------------------------------------------------------------------------- shared helpers
def tree_module(new: str, old: str):
    """The module `new` (this tree's layout: ago_runtime/predict, vocab, formats, geometry) or `old` (the
    baseline's flat ago_runtime), whichever layout the ago_runtime on PYTHONPATH has. Chosen by layout, not
    by trying imports: the editable install of the main checkout would answer a name the baseline lacks
    with the main checkout's module."""
    import importlib

    import ago_runtime

    reorganised = (Path(ago_runtime.__file__).parent / "predict").is_dir()
    return importlib.import_module(new if reorganised else old)


def model_config(name: str):
    from ago_train.model import ModelConfig

    Grid = tree_module("ago_runtime.geometry.grid", "ago_runtime.grid").Grid

    cfg = ModelConfig.preset("cpu")
    cfg.pretrained = False
    if name == "cpu@200x200x16":
        cfg.grid = Grid.occ3d().to_dict()
        cfg.tpv_h, cfg.tpv_w = 100, 100
    return cfg


def load_frame(rig_default):
    """The real nuScenes keyframe when present, else the exporter's synthetic frame."""
    if (SHARED_SAMPLE / "mmdet3d_info.pkl").is_file():
        load_mmdet3d_info = tree_module("ago_runtime.formats.mmdet3d_info", "ago_runtime.mmdet3d_info").load_mmdet3d_info

        f = load_mmdet3d_info(SHARED_SAMPLE / "mmdet3d_info.pkl", SHARED_SAMPLE)[0]
        return f.images, f.rig, f"nuScenes {f.token} (1600x900)"
    from ago_export.export import synthetic_frame

    return synthetic_frame(rig_default)


def peak_rss_mib() -> float:
    """VmHWM of this process (ru_maxrss would carry the parent's peak over fork + exec)."""
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def loadavg() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


# ---------------------------------------------------------------------------- children (either tree)
def child_export(config: str, out: str, parity: str) -> dict:
    """Random checkpoint of `config` -> bundle at `out` with this process's code (either tree)."""
    from ago_export.testing import random_checkpoint

    ckpt = random_checkpoint(Path(out).with_suffix(".pt"), model_config(config), prompts="cw", seed=0)
    return child_export_ckpt(str(ckpt), out, parity)


def child_export_ckpt(ckpt: str, out: str, parity: str) -> dict:
    """A checkpoint -> bundle at `out` with this process's code (either tree)."""
    from ago_export.export import export_bundle

    t = time.perf_counter()
    meta = export_bundle(Path(ckpt), Path(out), bank_prompts=[], real_frame=parity == "real", parity=parity != "none",
                         log=lambda s: None)
    return {"export_s": time.perf_counter() - t, "parity": meta.get("parity", {}), "checkpoint": ckpt,
            "step": meta.get("checkpoint", {}).get("step")}


def child_frame(bundle: str, reps: int, cache: str) -> dict:
    """First frame of a new process, steady state, planes alone, bank swap, peak RSS."""
    os.environ["AGO_CACHE_DIR"] = cache
    t0 = time.perf_counter()
    bank_module = tree_module("ago_runtime.vocab.bank", "ago_runtime.bank")
    load_prompt_bank = getattr(bank_module, "load_prompt_bank", None) or bank_module.bank_for_prompts
    Predictor = tree_module("ago_runtime.predict.predictor", "ago_runtime.predictor").Predictor

    t1 = time.perf_counter()
    p = Predictor(bundle)
    t2 = time.perf_counter()
    images, rig, frame = load_frame(p.bundle.rig)
    bank = p.bundle.load_bank()
    t3 = time.perf_counter()
    x, m = p.prepare(images, rig)
    folded = p.fold(bank)
    t4 = time.perf_counter()
    first = p.predict_arrays(x, m, bank, "min-entropy", folded)
    t5 = time.perf_counter()
    rss_first = peak_rss_mib()
    steady, enc, heads = [], [], []
    for _ in range(reps):
        t = time.perf_counter()
        pr = p.predict_arrays(x, m, bank, "min-entropy", folded)
        steady.append(time.perf_counter() - t)
        enc.append(pr.timings["encoder"])
        heads.append(pr.timings["heads"])
    planes = []
    for _ in range(reps):
        t = time.perf_counter()
        p.encoder.plane_maps(x, m)
        planes.append(time.perf_counter() - t)
    pre = []
    for _ in range(reps):
        t = time.perf_counter()
        p.prepare(images, rig)
        pre.append(time.perf_counter() - t)
    # the frame `ago infer` gives for the training bank: the bundle's default identifier (this tree: none for a
    # closed-world bank, which skips the adapted branch); the baseline has no such rule (min-entropy always)
    default_id = p.bundle.identifier_for(bank) if hasattr(p.bundle, "identifier_for") else "min-entropy"
    steady_default = []
    if default_id != "min-entropy":
        for _ in range(reps):
            t = time.perf_counter()
            p.predict_arrays(x, m, bank, default_id, folded)
            steady_default.append(time.perf_counter() - t)
    # bank swap: a prompt file never seen before (cold text encoder session, cache miss)
    prompt = Path(cache) / f"swap_{time.time_ns()}.txt"
    prompt.parent.mkdir(parents=True, exist_ok=True)
    prompt.write_text(f"# {time.time_ns()}\n" + SWAP_PROMPTS)
    s0 = time.perf_counter()
    new_bank = load_prompt_bank(prompt, cache_dir=Path(cache) / "banks")
    s1 = time.perf_counter()
    new_folded = p.fold(new_bank)
    s2 = time.perf_counter()
    p.predict_arrays(x, m, new_bank, "min-entropy", new_folded)
    s3 = time.perf_counter()
    requery = None
    if "planes" in inspect.signature(p.predict_arrays).parameters:
        # a user re-querying the frame they just predicted with another never-seen prompt file: the frame's
        # planes are kept from its prediction (plane_maps), the rest (text encoder, fold, voxel stage, heads)
        # runs again
        pred_mod = tree_module("ago_runtime.predict.predictor", "ago_runtime.predictor")
        if hasattr(pred_mod, "FrameFeatures"):
            # the frame's features kept by its prediction (planes and every voxel's h)
            features = pred_mod.FrameFeatures()
            p.predict_arrays(x, m, bank, "min-entropy", folded, features=features)
            kept = {"features": features}
        else:
            kept = {"planes": p.encoder.plane_maps(x, m)}
        prompt2 = prompt.with_name(prompt.stem + "_requery.txt")
        prompt2.write_text(f"# {time.time_ns()}\n" + SWAP_PROMPTS.replace("mailbox", "post box"))
        r0 = time.perf_counter()
        bank2 = load_prompt_bank(prompt2, cache_dir=Path(cache) / "banks")
        r1 = time.perf_counter()
        folded2 = p.fold(bank2)
        r2 = time.perf_counter()
        p.predict_arrays(x, m, bank2, "min-entropy", folded2, **kept)
        r3 = time.perf_counter()
        requery = {"encode_s": r1 - r0, "fold_s": r2 - r1, "predict_s": r3 - r2, "total_s": r3 - r0,
                   "kept": sorted(kept), "kept_mib": kept["features"].nbytes / 2 ** 20 if "features" in kept else None}
    occupied = float(np.mean(first.semantics != first.free_index))
    med = statistics.median
    return {"frame": frame, "import_s": t1 - t0, "open_s": t2 - t1, "first_s": t5 - t4,
            "first_timings": first.timings, "steady_s": med(steady), "steady_min_s": min(steady),
            "encoder_s": med(enc), "heads_s": med(heads), "planes_s": med(planes), "voxels_s": med(enc) - med(planes),
            "preprocess_s": med(pre), "rss_mib": peak_rss_mib(), "rss_after_first_mib": rss_first,
            "swap": {"encode_s": s1 - s0, "fold_s": s2 - s1, "predict_s": s3 - s2, "total_s": s3 - s0},
            "requery": requery, "occupied_share": occupied, "default_identifier": default_id,
            "steady_default_s": med(steady_default) if steady_default else med(steady),
            "labels_sha": __import__("hashlib").sha256(first.semantics.tobytes()).hexdigest()[:12],
            "grid": list(p.grid.shape), "phrases": int(bank.num_phrases)}


def child_infer(bundle: str, dataset: str, out: str, picture: str, cache: str) -> dict:
    """`ago infer --images DATASET` in one process (run_infer): per-frame wall time."""
    import contextlib
    import inspect
    import io

    os.environ["AGO_CACHE_DIR"] = cache
    os.environ["AGO_NO_PROGRESS"] = "1"
    run_infer = tree_module("ago_runtime.predict.cli", "ago_runtime.cli_infer").run_infer

    kwargs = {}
    if "picture" in inspect.signature(run_infer).parameters:
        kwargs["picture"] = picture
    elif picture != "full":
        return {"skipped": f"this tree's run_infer has no picture option ({picture})"}
    t = time.perf_counter()
    with contextlib.redirect_stderr(io.StringIO()):
        files = run_infer(dataset, None, None, bundle, out, None, False, **kwargs)
    wall = time.perf_counter() - t
    frames = len([f for f in files if str(f).endswith(".npz")])
    return {"wall_s": wall, "frames": frames, "per_frame_s": wall / frames, "files": len(files)}


# ---------------------------------------------------------------------------- parent
def run_child(tree: Path, *args: str) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tree), str(REPO)]), AGO_NO_PROGRESS="1")
    r = subprocess.run([sys.executable, "-m", "benchmarks.runtime_speed", "--child", *args], capture_output=True,
                       text=True, env=env, cwd=tree)   # the tree's ago_runtime, this repository's benchmarks
    if r.returncode != 0:
        raise RuntimeError(f"child {args} in {tree} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def extract_baseline(dest: Path) -> Path:
    dest.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(REPO), "archive", BASELINE_COMMIT], capture_output=True, check=True)
    subprocess.run(["tar", "x", "-C", str(dest)], input=archive.stdout, check=True)
    return dest


def matmul_rates() -> dict:
    """Best fp32 GFLOP/s of onnxruntime here: MatMul n^3 (n = 1024, 2048, 3072) and a 3x3 Conv."""
    import onnxruntime as ort
    from onnx import TensorProto as TP
    from onnx import helper as H
    from onnx import numpy_helper as NH

    so = ort.SessionOptions()
    so.log_severity_level = 3
    rng = np.random.default_rng(0)
    g = H.make_graph([H.make_node("MatMul", ["A", "B"], ["y"])], "mm",
                     [H.make_tensor_value_info("A", TP.FLOAT, ["n", "n"]), H.make_tensor_value_info("B", TP.FLOAT, ["n", "n"])],
                     [H.make_tensor_value_info("y", TP.FLOAT, None)])
    mm = ort.InferenceSession(H.make_model(g, opset_imports=[H.make_opsetid("", 17)], ir_version=9).SerializeToString(),
                              so, providers=["CPUExecutionProvider"])
    best = {"matmul": 0.0, "conv3x3": 0.0}
    for n in (1024, 2048, 3072):
        a = rng.standard_normal((n, n), dtype=np.float32)
        mm.run(None, {"A": a, "B": a})
        t = min(_timed(lambda: mm.run(None, {"A": a, "B": a})) for _ in range(3))
        best["matmul"] = max(best["matmul"], 2 * n ** 3 / t / 1e9)
    w = NH.from_array(rng.standard_normal((64, 64, 3, 3)).astype(np.float32) * 0.05, "W")
    g = H.make_graph([H.make_node("Conv", ["x", "W"], ["y"], pads=[1, 1, 1, 1])], "conv",
                     [H.make_tensor_value_info("x", TP.FLOAT, [6, 64, 96, 176])], [H.make_tensor_value_info("y", TP.FLOAT, None)], [w])
    conv = ort.InferenceSession(H.make_model(g, opset_imports=[H.make_opsetid("", 17)], ir_version=9).SerializeToString(),
                                so, providers=["CPUExecutionProvider"])
    x = rng.standard_normal((6, 64, 96, 176), dtype=np.float32)
    conv.run(None, {"x": x})
    t = min(_timed(lambda: conv.run(None, {"x": x})) for _ in range(3))
    best["conv3x3"] = 2 * 6 * 96 * 176 * 64 * 64 * 9 / t / 1e9
    best["best"] = max(best["matmul"], best["conv3x3"])
    return best


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def frame_flops(config: str, phrases: int) -> dict:
    """Matmul + conv FLOPs of one frame (torch's flop counter): the model as today's bundle exports it
    (forward_hidden + both bank products; the format-2 graphs hold the same products) and this tree's
    PlanesGraph + VoxelsGraph (first decoder linear on the planes)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from ago_export.graphs import PlanesGraph, VoxelsReference

    cfg = model_config(config)
    torch.manual_seed(0)
    model = cfg.build().eval().requires_grad_(False)
    x = torch.zeros(1, 6, 3, cfg.image_height, cfg.image_width)
    from ago_runtime.geometry.camera import Rig
    from ago_runtime.geometry.preprocess import Preprocess

    m = torch.from_numpy(Preprocess(cfg.image_width, cfg.image_height).ego2img(Rig.nuscenes_like(1600, 900))[None])
    X, Y, Z = cfg.grid_obj().shape
    N = X * Y * Z
    Dh, C, Da = cfg.hidden_dim, cfg.embed_dim, cfg.adapter_hidden
    bank_flops = 2 * N * phrases * (Dh + Da)
    with torch.no_grad():
        with FlopCounterMode(display=False) as fc:
            model.planes(x, m)
        old_planes = fc.get_total_flops()
        # today's voxel graph: decoder (D -> Dh) + fused adapter (Dh -> Da) per voxel (decoder_out is folded)
        old_voxels = 2 * N * (cfg.tpv_dim * Dh + Dh * Da) + bank_flops
        pg = PlanesGraph(model).eval()
        with FlopCounterMode(display=False) as fc:
            planes = pg(x, m)
        new_planes = fc.get_total_flops()
        vg = VoxelsReference(model).eval()       # the voxel stages of one x row; the bank products run beside them
        with FlopCounterMode(display=False) as fc:
            vg(planes[0][:1], planes[1][:1], planes[2])
        new_voxels = fc.get_total_flops() * X + bank_flops
    return {"old_planes": old_planes, "old_voxels": old_voxels, "old_total": old_planes + old_voxels,
            "new_planes": new_planes, "new_voxels": new_voxels, "new_total": new_planes + new_voxels, "N": N,
            "C": C}


def make_dataset(work: Path, given: str | None) -> Path:
    if given:
        return Path(given)
    out = work / "synth12"
    r = subprocess.run([sys.executable, "-m", "ago_runtime", "synth", "--out", str(out), "--scenes", "2", "--frames", "6",
                        "--image-size", "704x396", "--grid", "100x100x8", "--seed", "5"], capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=str(REPO), AGO_NO_PROGRESS="1"))
    if r.returncode != 0:
        raise RuntimeError(r.stderr[-2000:])
    return out


def shipped_bundle_timing(work: Path, args, log) -> dict | None:
    """The shipped default bundle when it reads out on another grid than the cpu config's 100x100x8 (no
    format-2 baseline exists for it): its steady frame, first frame and RSS, and `ago infer` over the dataset
    (--picture none), new side only."""
    shipped = REPO / "ago_runtime" / "assets" / "default_bundle"
    if not (shipped / "bundle.json").is_file():
        return None
    meta = json.loads((shipped / "bundle.json").read_text())
    if meta["grid"]["shape"] == [100, 100, 8]:
        return None
    cache = str(work / "cache_shipped")
    run_child(REPO, "frame", str(shipped), "1", cache)
    frames = [run_child(REPO, "frame", str(shipped), str(args.reps), cache) for _ in range(args.rounds)]
    out = {"grid": meta["grid"]["shape"], "model_grid": (meta.get("model_grid") or meta["grid"])["shape"]}
    out.update({k: best_of(frames, k) for k in ("steady_s", "steady_default_s", "first_s", "open_s", "planes_s",
                                                "voxels_s", "heads_s", "rss_mib")})
    if not args.no_infer:
        ds = make_dataset(work, args.dataset)
        inf = [run_child(REPO, "infer", str(shipped), str(ds), str(work / f"inf_s{r}"), "none", cache)
               for r in range(args.rounds)]
        out["infer_per_frame_s"] = best_of(inf, "per_frame_s")
        out["infer_frames"] = inf[0]["frames"]
    log(f"shipped bundle: {out}")
    return out


def best_of(rounds: list[dict], key: str) -> float:
    return min(r[key] for r in rounds)


def bench_config(name: str, base: Path, work: Path, args, log) -> dict:
    res: dict = {"name": name}
    shipped_new = REPO / "ago_runtime" / "assets" / "default_bundle"
    cache_b, cache_n = str(work / "cache_base"), str(work / "cache_new")
    # --- bundles
    if name == "cpu" and args.baseline == "shipped":
        base_bundle = base / "ago_runtime" / "assets" / "default_bundle"
        res["baseline_bundle"] = "shipped default bundle of the baseline tree (format 2, trained)"
    else:
        base_bundle = work / f"base_{name}"
        res["baseline_export"] = run_child(base, "export", name, str(base_bundle), "none")
        res["baseline_bundle"] = "baseline code's export of a random checkpoint (format 2)"
    new_meta = shipped_new / "bundle.json"
    use_shipped = False
    if name == "cpu" and new_meta.is_file():
        meta = json.loads(new_meta.read_text())
        from ago_runtime.predict.bundle import BUNDLE_FORMAT_VERSION

        use_shipped = meta.get("format_version") == BUNDLE_FORMAT_VERSION and meta["grid"]["shape"] == [100, 100, 8]
    if use_shipped:
        new_bundle = shipped_new
        res["new_bundle"] = "shipped default bundle of this tree (format 3, trained)"
    elif {"cpu": args.ckpt_cpu, "cpu@200x200x16": args.ckpt_200}.get(name):
        ckpt = args.ckpt_cpu if name == "cpu" else args.ckpt_200
        new_bundle = work / f"new_{name}"
        res["new_export"] = run_child(REPO, "export_ckpt", str(Path(ckpt).resolve()), str(new_bundle),
                                      "real" if args.parity else "none")
        steps = res["new_export"]["step"]
        res["new_bundle"] = (f"this tree's export of the trained cpu checkpoint ({steps} steps; --ckpt-cpu) on its model "
                             "grid (format 3)" if name == "cpu" else f"this tree's export of a 200x200x16 model trained "
                             f"{steps} steps on the synthetic world (format 3; --ckpt-200)")
    else:
        new_bundle = work / f"new_{name}"
        res["new_export"] = run_child(REPO, "export", name, str(new_bundle), "real" if args.parity else "none")
        res["new_bundle"] = "this tree's export of a random checkpoint (format 3)"
    log(f"{name}: bundles ready (load {loadavg()})")
    # --- frames, alternating
    base_rounds, new_rounds = [], []
    for r in range(args.rounds):
        for tree, bundle, cache, rounds in ((base, base_bundle, cache_b, base_rounds), (REPO, new_bundle, cache_n, new_rounds)):
            if r == 0:   # the first child of each side fills its caches (optimised graphs, text encoder)
                run_child(tree, "frame", str(bundle), "1", cache)
            rounds.append(run_child(tree, "frame", str(bundle), str(args.reps), cache))
        log(f"{name}: round {r + 1}: base {base_rounds[-1]['steady_s']:.3f} s, new {new_rounds[-1]['steady_s']:.3f} s "
            f"(load {loadavg()})")
    res["base_rounds"], res["new_rounds"] = base_rounds, new_rounds
    for side, rounds in (("base", base_rounds), ("new", new_rounds)):
        res[side] = {k: best_of(rounds, k) for k in ("steady_s", "steady_min_s", "first_s", "open_s", "planes_s",
                                                     "voxels_s", "heads_s", "encoder_s", "preprocess_s", "rss_mib",
                                                     "steady_default_s")}
        res[side]["default_identifier"] = rounds[0]["default_identifier"]
        res[side]["swap_total_s"] = min(r["swap"]["total_s"] for r in rounds)
        res[side]["swap_encode_s"] = min(r["swap"]["encode_s"] for r in rounds)
        res[side]["swap_predict_s"] = min(r["swap"]["predict_s"] for r in rounds)
        res[side]["first_ratio"] = min(r["first_s"] / r["steady_s"] for r in rounds)
        req = [r["requery"] for r in rounds if r.get("requery")]
        if req:
            res[side]["requery_total_s"] = min(q["total_s"] for q in req)
            res[side]["requery_encode_s"] = min(q["encode_s"] for q in req)
            res[side]["requery_predict_s"] = min(q["predict_s"] for q in req)
        if all("occupied_share" in r for r in rounds):
            res[side]["occupied_share"] = rounds[0]["occupied_share"]
    res["frame"] = new_rounds[0]["frame"]
    res["phrases"] = new_rounds[0]["phrases"]
    res["speedup"] = res["base"]["steady_s"] / res["new"]["steady_s"]
    # --- ago infer over a 12-frame dataset
    if name == "cpu" and not args.no_infer:
        ds = make_dataset(work, args.dataset)
        inf: dict = {"base": [], "new": {p: [] for p in ("full", "bev", "none")}}
        for r in range(args.rounds):
            inf["base"].append(run_child(base, "infer", str(base_bundle), str(ds), str(work / f"inf_b{r}"), "full", cache_b))
            for pic in ("full", "bev", "none"):
                inf["new"][pic].append(run_child(REPO, "infer", str(new_bundle), str(ds), str(work / f"inf_n{r}{pic}"),
                                                 pic, cache_n))
            log(f"{name}: infer round {r + 1}: base {inf['base'][-1]['per_frame_s']:.3f} s/frame, new full "
                f"{inf['new']['full'][-1]['per_frame_s']:.3f} (load {loadavg()})")
        res["infer"] = {"base": best_of(inf["base"], "per_frame_s"),
                        "new": {p: best_of(v, "per_frame_s") for p, v in inf["new"].items()},
                        "frames": inf["base"][0]["frames"], "dataset": str(ds) if args.dataset else
                        "ago synth --scenes 2 --frames 6 --image-size 704x396 --grid 100x100x8 --seed 5"}
    return res


def write_report(res: dict, path: Path) -> str:
    def met(ok: bool) -> str:
        return "met" if ok else "MISSED"

    R = res["rates"]
    L = ["# Runtime speed: bundle format 3 vs today's format 2, side by side\n",
         f"Command: `{res['command']}`  ",
         f"Machine: {res['machine']}; load average (1, 5, 15 min) at start {res['load_start']}, at end {res['load_end']} "
         "(other engineers' jobs share these cores; baseline and new children alternate and each figure is the best "
         "of the rounds' medians).  ",
         f"Baseline: commit {BASELINE_COMMIT} (`git archive`, run with PYTHONPATH there) — today's code and format-2 "
         "bundle. New: this tree.  ",
         f"Frame: {res['frame']}; bank: the bundle's training bank ({res['configs'][0]['phrases']} phrases).  ",
         f"Best fp32 rate measured here (onnxruntime): MatMul {R['matmul']:.0f} GFLOP/s, 3x3 Conv {R['conv3x3']:.0f} "
         f"GFLOP/s -> **{R['best']:.0f} GFLOP/s**; FLOP bound = matmul + conv FLOPs of a frame / that rate.\n"]
    rate = max(R["best"], REFERENCE_RATE)
    L.append(f"The FLOP bound uses the higher of the rate measured in this run and {REFERENCE_RATE:.0f} GFLOP/s (the "
             "rate measured on the quiet machine in the issue): a loaded machine measures a lower rate, which "
             f"would flatter the achieved fraction. Here: **{rate:.0f} GFLOP/s**.\n")
    L.append("## Steady-state frame (from preprocessed tensors: graphs + numpy heads)\n")
    L.append("| config | baseline bundle | new bundle | baseline s | new s (planes + voxels + heads) | speedup (target >= 2x) | "
             "GFLOP today / new | FLOP bound ms (today / new) | achieved fraction of the bound (target >= 30 %) |")
    L.append("|---|---|---|---|---|---|---|---|---|")
    for c in res["configs"]:
        f, b, n = c["flops"], c["base"], c["new"]
        bound_old = f["old_total"] / rate / 1e9 * 1e3
        bound_new = f["new_total"] / rate / 1e9 * 1e3
        frac_new = bound_new / 1e3 / n["steady_s"]
        frac_old = bound_old / 1e3 / n["steady_s"]
        c["fraction"] = frac_new
        L.append(f"| {c['name']} | {c['baseline_bundle']} | {c['new_bundle']} | {b['steady_s']:.3f} | "
                 f"**{n['steady_s']:.3f}** ({n['planes_s']:.3f} + {n['voxels_s']:.3f} + {n['heads_s']:.3f}) | "
                 f"**{c['speedup']:.2f}x** ({met(c['speedup'] >= TARGETS['speedup'])}) | "
                 f"{f['old_total'] / 1e9:.1f} / {f['new_total'] / 1e9:.1f} | {bound_old:.0f} / {bound_new:.0f} | "
                 f"**{frac_new:.0%}** of the new graphs' bound ({met(frac_new >= TARGETS['bound_share'])}); "
                 f"{frac_old:.0%} of today's |")
    L.append("\nBaseline split (planes + voxels + heads): " + "; ".join(
        f"{c['name']} {c['base']['planes_s']:.3f} + {c['base']['voxels_s']:.3f} + {c['base']['heads_s']:.3f} s"
        for c in res["configs"]) + ". Preprocessing (resize + normalise, not in the frame): " + "; ".join(
        f"{c['name']} {c['base']['preprocess_s'] * 1e3:.0f} / {c['new']['preprocess_s'] * 1e3:.0f} ms" for c in res["configs"])
        + " (baseline / new).\n")
    L.append("The frames above run the open-world identifier (min-entropy) on both sides: the adapted branch on "
             "the voxels that need it, what an open-world prompt file gets. With the training bank `ago infer` takes "
             "the bundle's default identifier (this tree: `none` for a closed-world bank, which skips the adapted "
             "branch; the baseline has no such rule and runs min-entropy):\n")
    L.append("| config | baseline s (min-entropy) | new s, default identifier | speedup |")
    L.append("|---|---|---|---|")
    for c in res["configs"]:
        b, n = c["base"], c["new"]
        if "steady_default_s" in n:
            sp = b["steady_s"] / n["steady_default_s"]
            L.append(f"| {c['name']} | {b['steady_s']:.3f} | {n['steady_default_s']:.3f} "
                     f"({n.get('default_identifier', '?')}) | {sp:.2f}x |")
    L.append("")
    L.append("## First frame of a new process, bank swap, peak RSS\n")
    L.append("| config | side | open s (Predictor(bundle)) | first frame s | first / steady (target <= 1.5) | "
             "swap s: encode + fold + first prediction (target < 1 s) | peak RSS MiB (target) |")
    L.append("|---|---|---|---|---|---|---|")
    for c in res["configs"]:
        rss_t = TARGETS["rss_mib"][c["name"]]
        for side in ("base", "new"):
            s = c[side]
            tag = side == "new"
            L.append(f"| {c['name']} | {'new' if tag else 'baseline'} | {s['open_s']:.2f} | {s['first_s']:.3f} | "
                     f"{s['first_ratio']:.2f}" + (f" ({met(s['first_ratio'] <= TARGETS['first_ratio'])})" if tag else "") +
                     f" | {s['swap_total_s']:.3f} ({s['swap_encode_s']:.3f} + {s['swap_predict_s']:.3f})" +
                     (f" ({met(s['swap_total_s'] < TARGETS['swap_s'])})" if tag else "") +
                     f" | {s['rss_mib']:.0f}" + (f" (<= {rss_t}: {met(s['rss_mib'] <= rss_t)})" if tag else "") + " |")
    L.append("\nOpen: bundle load + onnxruntime sessions (new: cached optimised graphs + one warm-up run of each graph). "
             "First frame: the first `predict_arrays` after that. Swap: a never-seen prompt file through a new text "
             "encoder session (new: its optimised graph cached like the bundle's), folded, then one whole prediction "
             "with it (planes and voxel stage: a whole frame). Peak RSS: VmHWM of the child (bundle, frame, warm-up, "
             "predictions).\n")
    req = [c for c in res["configs"] if "requery_total_s" in c["new"]]
    if req:
        L.append("**Re-query of the same frame** (new only: `predict_arrays(..., features=FrameFeatures)` with the "
                 "planes and every voxel's decoder output h that the frame's prediction kept; a user asking the frame "
                 "they just saw about another never-seen prompt file; the peak RSS above includes what is kept): " +
                 "; ".join(
                     f"{c['name']} **{c['new']['requery_total_s']:.3f} s** ({c['new']['requery_encode_s']:.3f} encode + "
                     f"{c['new']['requery_predict_s']:.3f} voxel stage and heads) "
                     f"({met(c['new']['requery_total_s'] < TARGETS['swap_s'])} against the < 1 s swap target)"
                     for c in req) + ".\n")
    occ = [c for c in res["configs"] if "occupied_share" in c["new"]]
    if occ:
        L.append("**Occupied share** (voxels the main branch calls occupied: the only ones the new runtime runs the "
                 "adapter's stages and the adapted bank's product on; the voxel stage's cost depends on it): " +
                 "; ".join(f"{c['name']} {c['new']['occupied_share']:.1%} ({c['new_bundle']})" for c in occ) + ".\n")
    inf = next((c.get("infer") for c in res["configs"] if c.get("infer")), None)
    if inf:
        cpu = next(c for c in res["configs"] if c.get("infer"))
        # the steady state of the frame run_infer computes: the bundle's default identifier for its training bank
        steady = cpu["new"].get("steady_default_s", cpu["new"]["steady_s"])
        L.append(f"## `ago infer --images DATASET` ({inf['frames']} frames, one process; {inf['dataset']})\n")
        L.append("| side | --picture | s per frame (wall of run_infer / frames) | speedup vs baseline (target >= 2x) | "
                 f"vs the new Predictor's steady state with the same identifier ({steady:.3f} s; target <= 1.3x) |")
        L.append("|---|---|---|---|---|")
        L.append(f"| baseline | (full PNG) | {inf['base']:.3f} | | {inf['base'] / cpu['base']['steady_s']:.2f}x of its own |")
        for pic, v in inf["new"].items():
            sp, rel = inf["base"] / v, v / steady
            L.append(f"| new | {pic} | **{v:.3f}** | **{sp:.2f}x** ({met(sp >= TARGETS['infer_speedup'])}) | "
                     f"{rel:.2f}x ({met(rel <= TARGETS['infer_vs_steady'])}) |")
        L.append("\nPer frame: bundle load and sessions, JPEG decode, resize + normalise, graphs, heads, npz and PNG "
                 "written (the new run_infer overlaps reading and writing with inference in threads), divided by the "
                 "number of frames.\n")
    sh = res.get("shipped")
    if sh:
        grid, mgrid = "x".join(map(str, sh["grid"])), "x".join(map(str, sh["model_grid"]))
        L.append(f"## The shipped default bundle (model {mgrid}, read out at {grid}; no baseline)\n")
        L.append("| steady frame s, min-entropy (planes + voxels + heads) | steady, default identifier | open s | "
                 "first frame s (first / steady) | peak RSS MiB | `ago infer` s per frame (--picture none) |")
        L.append("|---|---|---|---|---|---|")
        inf_txt = (f"{sh['infer_per_frame_s']:.3f} ({sh['infer_per_frame_s'] / sh['steady_default_s']:.2f}x the steady "
                   "default)" if "infer_per_frame_s" in sh else "–")
        L.append(f"| {sh['steady_s']:.3f} ({sh['planes_s']:.3f} + {sh['voxels_s']:.3f} + {sh['heads_s']:.3f}) | "
                 f"{sh['steady_default_s']:.3f} | {sh['open_s']:.2f} | {sh['first_s']:.3f} "
                 f"({sh['first_s'] / sh['steady_s']:.2f}) | {sh['rss_mib']:.0f} | {inf_txt} |")
        L.append("\nThe default bundle reads its 100x100x8 model's TPV planes at Occ3D's 0.4 m voxel centres "
                 "(`ago export --readout-grid`, docs/training.md: +1.1-1.5 mIoU): 8x the voxels through the voxel "
                 "stage. The cpu rows above time the same checkpoint exported on its model grid (--ckpt-cpu).\n")
    par = [c for c in res["configs"] if c.get("new_export", {}).get("parity")]
    if par:
        L.append("## Parity of the new export (ago_export.parity, torch vs onnxruntime)\n")
        for c in par:
            p = c["new_export"]["parity"].get("fp32", {})
            if p:
                L.append(f"- {c['name']}: {p['frame']}: rel err F {p['rel_err_feat']:.1e}, F~ {p['rel_err_feat_adapted']:.1e}; "
                         f"argmax agreement main {p['agreement_main']:.4%}, adapted {p['agreement_adapted']:.4%}, "
                         f"identifier {p['agreement_identifier']:.4%}")
        L.append("")
    text = "\n".join(L) + "\n"
    from ago_runtime.atomic import write_text

    write_text(path, text)
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--configs", default="cpu,cpu@200x200x16")
    ap.add_argument("--reps", type=int, default=7, help="steady-state predictions per child")
    ap.add_argument("--rounds", type=int, default=2, help="alternating baseline/new children per measurement")
    ap.add_argument("--baseline", choices=("shipped", "export"), default="shipped",
                    help="cpu baseline: the baseline tree's shipped format-2 bundle, or its export of the random checkpoint")
    ap.add_argument("--dataset", default=None, help="nuScenes-layout dataset for the infer timing (default: make 12 frames)")
    ap.add_argument("--no-infer", action="store_true")
    ap.add_argument("--ckpt-200", default=None,
                    help="a trained cpu@200x200x16 checkpoint for the new side of that config (realistic occupied "
                         "share; the baseline's time does not depend on the weights), instead of random weights")
    ap.add_argument("--ckpt-cpu", default=None,
                    help="a trained cpu checkpoint for the new side of the cpu config when the shipped bundle is not on "
                         "the 100x100x8 grid (it reads out on 200x200x16): exported on its model grid")
    ap.add_argument("--no-parity", dest="parity", action="store_false", help="skip the new export's torch parity check")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--report-only", type=Path, default=None, help="rewrite the report from a results .json")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.report_only:
        print(write_report(json.loads(args.report_only.read_text()), args.out))
        return
    if args.child:
        kind, *rest = args.child
        fn = {"export": child_export, "export_ckpt": child_export_ckpt, "frame": child_frame,
              "infer": child_infer}[kind]
        if kind == "frame":
            rest[1] = int(rest[1])
        print(json.dumps(fn(*rest)))
        return
    log = lambda s: print(s, flush=True)   # noqa: E731
    load_start = loadavg()
    rates = matmul_rates()
    log(f"fp32 rates {rates} (load {loadavg()})")
    configs = []
    with tempfile.TemporaryDirectory(prefix="ago_bench_") as tmp:
        work = Path(tmp)
        base = extract_baseline(work / "baseline")
        for name in args.configs.split(","):
            c = bench_config(name, base, work, args, log)
            c["flops"] = frame_flops(name, c["phrases"])
            configs.append(c)
            log(json.dumps({k: v for k, v in c.items() if k not in ("base_rounds", "new_rounds")}))
        shutil.rmtree(base, ignore_errors=True)
        shipped = shipped_bundle_timing(work, args, log)
    cpu = platform.processor() or platform.machine()
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    res = {"command": "python " + " ".join([Path(sys.argv[0]).as_posix()] + sys.argv[1:]),
           "machine": f"{cpu}, {os.cpu_count()} cores", "load_start": load_start, "load_end": loadavg(),
           "rates": rates, "configs": configs, "frame": configs[0]["frame"], "shipped": shipped}
    (args.out.with_suffix(".json")).write_text(json.dumps(res, indent=1, default=str))
    print(write_report(res, args.out))


if __name__ == "__main__":
    main()
