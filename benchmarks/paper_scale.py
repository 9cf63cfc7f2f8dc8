"""The runtime at the paper's scale on this CPU (issue 39): the `full` preset (1600x928 input, 200x200x16 grid,
the preset's widths) through the runtime, this tree against a baseline commit, side by side in one run.

    python -m benchmarks.paper_scale [--baseline a2187f0] [--reps 3] [--rounds 2] [--profile] [--int8] [--openvino]
        # writes benchmarks/results/paper_scale.md (+ .json)

The weights are random (the full preset's TPV encoder and heads; the EfficientNet-Lite0 backbone without its
ImageNet weights): only the cost is measured, and the random model calls every voxel occupied, the runtime's
worst case. One random checkpoint is made; each side exports it with its own code (the baseline tree is
extracted with `git archive` and run with PYTHONPATH pointing there; export without the torch parity check).
Frames are predicted in fresh child processes that alternate between the sides, each figure the best of the
rounds (a load spike on this shared machine hits both sides alike). Per side: bundle open, first frame, steady
frame (median of --reps), the planes graph alone (onnxruntime, from the preprocessed tensors), peak RSS (VmHWM),
and the labels, compared voxel by voxel (argmax agreement). The frame is the real nuScenes keyframe of
../shared (1600x900, six cameras) when present, else the exporter's synthetic frame.
FLOP bound: matmul + conv FLOPs of one frame (torch's flop counter on the exported modules) / the best fp32
GFLOP/s onnxruntime reaches here (runtime_speed.py's MatMul/Conv probe). --profile adds onnxruntime's
per-operator split of the planes graph (new side).
--int8 adds a third side: this tree's bundle with an int8 variant (`Predictor(bundle, int8=True)`, what `ago infer
--int8` runs): the planes graph static QDQ (benchmarks.int8_static's recipe) and every voxel stage dynamic int8.
Its activation ranges are fixed (benchmarks.int8_static.UNCALIBRATED_RANGE), not calibrated: onnxruntime's
calibrator does not fit this machine's memory at this scale (benchmarks/results/int8_static_paper.md), and the int8
kernels' speed does not depend on the range values. So its label agreement with fp32 is that of an uncalibrated
random-weight model: a check that it runs end to end, not a measure of int8 accuracy.
--openvino (needs the `openvino` extra) adds this tree's fp32 bundle with its planes graph on OpenVINO's CPU device
(`Predictor(bundle, device="openvino")`, what `ago infer --device openvino` runs; the voxel stages stay on
onnxruntime, ago_runtime.providers.stage_target) and, with --int8, the int8 bundle the same way (`ago infer --int8
--device openvino`). The report has one row per side, its labels compared with this tree's fp32.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED_SAMPLE = REPO.parent / "shared" / "data" / "nuscenes-sample"
RESULTS = REPO / "benchmarks" / "results" / "paper_scale.md"


def peak_rss_mib() -> float:
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def require_openvino() -> None:
    """The openvino package, checked before any work: one `error:` line and exit 2 without it."""
    from ago_runtime.errors import AgoInputError
    from ago_runtime.providers import Device, check_device

    try:
        check_device(Device.OPENVINO)
    except AgoInputError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)


def load_frame():
    if (SHARED_SAMPLE / "mmdet3d_info.pkl").is_file():
        from ago_runtime.formats.mmdet3d_info import load_mmdet3d_info

        f = load_mmdet3d_info(SHARED_SAMPLE / "mmdet3d_info.pkl", SHARED_SAMPLE)[0]
        return f.images, f.rig, f"nuScenes keyframe {f.token} (six 1600x900 images)"
    from ago_export.export import synthetic_frame
    from ago_runtime.geometry.camera import Rig

    images, rig, name = synthetic_frame(Rig.nuscenes_like(1600, 900))
    return images, rig, name


def time_predictions(p, x, m, bank, identifier, reps: int):
    """-> (first frame s, [steady s] * reps, the last Prediction) of Predictor `p` on preprocessed x, m."""
    t = time.perf_counter()
    pred = p.predict_arrays(x, m, bank, identifier)
    first_s = time.perf_counter() - t
    steady = []
    for _ in range(reps):
        t = time.perf_counter()
        pred = p.predict_arrays(x, m, bank, identifier)
        steady.append(time.perf_counter() - t)
    return first_s, steady, pred


def predictor_frames(open_predictor, reps: int, labels_out: str):
    """The frame of `load_frame()` through a Predictor: open it (`open_predictor()`, timed), predict once (first
    frame) and `reps` times (steady), save the labels to `labels_out` (.npy).
    -> (predictor, x, m, bank, last prediction, record: open_s, first_s, steady_s (median), steady_all_s, rss_mib
    (peak RSS so far), frame, identifier)."""
    import numpy as np

    images, rig, frame_name = load_frame()
    t = time.perf_counter()
    p = open_predictor()
    open_s = time.perf_counter() - t
    bank = p.bundle.load_bank()
    identifier = p.bundle.identifier_for(bank)
    x, m = p.prepare(images, rig)
    first_s, steady, pred = time_predictions(p, x, m, bank, identifier, reps)
    np.save(labels_out, pred.semantics)
    record = {"open_s": open_s, "first_s": first_s, "steady_s": float(np.median(steady)), "steady_all_s": steady,
              "rss_mib": peak_rss_mib(), "frame": frame_name, "identifier": str(identifier)}
    return p, x, m, bank, pred, record


# ---------------------------------------------------------------------------- children (either tree)
def child_checkpoint(path: str) -> dict:
    from ago_export.testing import random_checkpoint

    random_checkpoint(Path(path), "full", prompts="cw", seed=0)
    return {"checkpoint": path}


def child_export(ckpt: str, out: str) -> dict:
    from ago_export.export import export_bundle

    t = time.perf_counter()
    export_bundle(Path(ckpt), Path(out), bank_prompts=[], parity=False, log=lambda s: None)
    return {"export_s": time.perf_counter() - t, "export_rss_mib": peak_rss_mib()}


def child_int8(bundle: str, out: str) -> dict:
    """A copy of `bundle` at `out` with an int8 variant: planes static QDQ with fixed ranges, stages dynamic."""
    from ago_export.quantize import quantize_encoder, quantize_planes_static
    from ago_runtime.predict.bundle import Bundle
    from benchmarks.int8_static import UNCALIBRATED_RANGE, variant_bundle

    planes, stages = Bundle.load(bundle).encoder_graphs()
    t = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ago-paper-int8-") as tmp:
        q_planes = quantize_planes_static(planes.path, Path(tmp) / "planes.onnx", [],
                                          uncalibrated_range=UNCALIBRATED_RANGE)
        q_stages = {st.spec.file: quantize_encoder(st.path, Path(tmp) / f"{st.spec.file}.onnx") for st in stages}
        variant_bundle(Path(bundle), Path(out), q_planes, q_stages)
    return {"quantise_s": time.perf_counter() - t, "quantise_rss_mib": peak_rss_mib(),
            "range": list(UNCALIBRATED_RANGE)}


def child_frame(bundle: str, reps: int, cache: str, labels_out: str, profile: str, variant: str = "") -> dict:
    """variant: "" (fp32), "openvino" (the planes graph on OpenVINO's CPU device), "int8" or "int8-openvino"."""
    os.environ["AGO_CACHE_DIR"] = cache
    import numpy as np
    import onnxruntime as ort

    from ago_runtime.predict.predictor import Predictor

    int8, device = variant.startswith("int8"), ("openvino" if variant.endswith("openvino") else "cpu")
    p, x, m, bank, pred, record = predictor_frames(lambda: Predictor(bundle, int8=int8, device=device), reps,
                                                   labels_out)
    # (record's peak RSS is taken before the second planes session below) the planes graph alone, in a session of
    # its own with the runtime's options; on OpenVINO the Predictor's own planes session
    from ago_runtime.cache import session_options

    so = session_options()
    if profile:
        so.enable_profiling = True
        so.profile_file_prefix = profile
    planes_graph = p.bundle.encoder_graphs("int8" if int8 else None)[0].path
    sess = (p.encoder.planes if device == "openvino"
            else ort.InferenceSession(str(planes_graph), so, providers=["CPUExecutionProvider"]))
    feed = dict(zip([i.name for i in sess.get_inputs()], [x, m]))
    sess.run(None, feed)
    planes = []
    for _ in range(max(1, reps - 1)):
        t = time.perf_counter()
        sess.run(None, feed)
        planes.append(time.perf_counter() - t)
    prof_file = sess.end_profiling() if profile else None
    return {**record, "planes_s": float(np.median(planes)),
            "occupied_share": float((pred.semantics != bank.num_classes).mean()),
            "shape": list(pred.semantics.shape), "profile": prof_file}


def child_flops() -> dict:
    """Matmul + conv FLOPs of one frame of the full preset: the planes (backbone, FPN, TPV encoder) and the
    per-voxel decoder + adapter + the bank products of the training bank's phrases."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from ago_runtime.geometry.camera import Rig
    from ago_runtime.geometry.preprocess import Preprocess
    from ago_runtime.vocab.bank import load_prompt_bank
    from ago_runtime.vocab.prompts import parse_prompt_file
    from ago_train.model import ModelConfig

    cfg = ModelConfig.preset("full")
    cfg.pretrained = False
    torch.manual_seed(0)
    model = cfg.build().eval().requires_grad_(False)
    x = torch.zeros(1, 6, 3, cfg.image_height, cfg.image_width)
    m = torch.from_numpy(Preprocess(cfg.image_width, cfg.image_height).ego2img(Rig.nuscenes_like(1600, 900))[None])
    with torch.no_grad(), FlopCounterMode(display=False) as fc:
        model.planes(x, m)
    planes = fc.get_total_flops()
    X, Y, Z = cfg.grid_obj().shape
    n = X * Y * Z
    phrases = len(load_prompt_bank(parse_prompt_file("cw")).phrase_class)
    d, dh, da = cfg.tpv_dim, cfg.hidden_dim, cfg.adapter_hidden
    decoder = 2 * n * (d * dh + dh * dh * (cfg.decoder_layers - 1))
    adapter = 2 * n * (dh * da + da * da * (cfg.adapter_depth - 1))
    main = decoder + 2 * n * phrases * dh          # the main branch: decoder + its bank product, every voxel
    adapted = adapter + 2 * n * phrases * da       # the adapted branch, if it ran on every voxel
    return {"planes": planes, "voxels": main, "voxels_note": f"decoder + main bank product ({phrases} phrases) on "
            f"{n} voxels", "adapted_all": adapted, "total": planes + main}


def child_rate() -> dict:
    from benchmarks.runtime_speed import matmul_rates

    return matmul_rates()


CHILDREN = {"checkpoint": child_checkpoint, "export": child_export, "int8": child_int8, "frame": child_frame,
            "flops": child_flops, "rate": child_rate}


# side -> (child_frame's variant, the bundle folder it reads in --work, how the report names it)
SIDES = {
    "base": ("", "bundle_base", "baseline"),
    "new": ("", "bundle_new", "this tree, fp32"),
    "openvino": ("openvino", "bundle_new", "this tree, fp32, planes graph on OpenVINO"),
    "int8": ("int8", "bundle_int8", "this tree, int8"),
    "int8_openvino": ("int8-openvino", "bundle_int8", "this tree, int8, planes graph on OpenVINO"),
}


def run_child(tree: Path, *args: str) -> dict:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), str(REPO)]), "AGO_NO_PROGRESS": "1"}
    r = subprocess.run([sys.executable, "-m", "benchmarks.paper_scale", "--child", *args], capture_output=True,
                       text=True, env=env, cwd=str(tree))   # the tree's ago_runtime, this repository's benchmarks
    if r.returncode != 0:
        raise SystemExit(f"child {args[0]} in {tree} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def op_split(profile_file: str, top: int = 8) -> list[tuple[str, float]]:
    import collections

    events = json.loads(Path(profile_file).read_text())
    by_op: collections.Counter = collections.Counter()
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            by_op[e["args"]["op_name"]] += e["dur"]
    total = sum(by_op.values()) or 1
    return [(op, 100.0 * us / total) for op, us in by_op.most_common(top)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baseline", default="a2187f0", help="git commit of the code to compare against")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--work", type=Path, default=REPO / "work" / "paper_scale")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--int8", action="store_true", help="a third side: this tree's int8 variant (see the doc)")
    ap.add_argument("--openvino", action="store_true", help="more sides: the planes graph on OpenVINO's CPU device, "
                    "fp32 (and int8 with --int8; see the doc)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        name, *rest = args.child
        fn = CHILDREN[name]
        if name == "frame":
            rest = [rest[0], int(rest[1]), *rest[2:]]
        print(json.dumps(fn(*rest)))
        return

    import numpy as np

    if args.openvino:
        require_openvino()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    log = lambda s: print(f"[{time.strftime('%H:%M:%S')}] {s}", flush=True)  # noqa: E731
    base = Path(tempfile.mkdtemp(prefix="ago-base-"))
    archive = subprocess.run(["git", "-C", str(REPO), "archive", args.baseline], capture_output=True, check=True)
    subprocess.run(["tar", "x", "-C", str(base)], input=archive.stdout, check=True)
    ckpt = work / "full_random.pt"
    if not ckpt.is_file():
        run_child(REPO, "checkpoint", str(ckpt))
    from benchmarks.default_bundle_towns import cpu_line

    res: dict = {"baseline": args.baseline, "command": "python -m benchmarks.paper_scale " + " ".join(sys.argv[1:]),
                 "cpu": cpu_line(),
                 "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "load_start": os.getloadavg()[0]}
    sides = {"base": base, "new": REPO}
    for side, tree in sides.items():
        res[f"{side}_export"] = run_child(tree, "export", str(ckpt), str(work / f"bundle_{side}"))
        log(f"{side}: exported in {res[f'{side}_export']['export_s']:.1f} s")
    if args.int8:
        shutil.rmtree(work / "bundle_int8", ignore_errors=True)
        res["int8_quantise"] = run_child(REPO, "int8", str(work / "bundle_new"), str(work / "bundle_int8"))
        log(f"int8: quantised in {res['int8_quantise']['quantise_s']:.1f} s")
        sides["int8"] = REPO
    if args.openvino:
        sides = {**{k: v for k, v in sides.items() if k != "int8"}, "openvino": REPO,
                 **({"int8": REPO, "int8_openvino": REPO} if args.int8 else {})}
    rounds: dict = {side: [] for side in sides}
    for r in range(args.rounds):
        for side, tree in sides.items():
            cache = str(work / f"cache_{side}")
            prof = str(work / "prof_new") if (args.profile and side == "new" and r == 0) else ""
            variant, folder, _ = SIDES[side]
            rounds[side].append(run_child(tree, "frame", str(work / folder), str(args.reps), cache,
                                          str(work / f"labels_{side}.npy"), prof, variant))
            log(f"{side} round {r + 1}: steady {rounds[side][-1]['steady_s']:.2f} s (load {os.getloadavg()[0]:.1f})")
    for side in sides:
        rs = rounds[side]
        res[side] = {k: min(x[k] for x in rs) for k in ("open_s", "first_s", "steady_s", "planes_s", "rss_mib")}
        res[side]["occupied_share"] = rs[0]["occupied_share"]
        res[side]["identifier"] = rs[0]["identifier"]
        res[side]["rounds_steady_s"] = [x["steady_s"] for x in rs]
    res["sides"] = list(sides)
    res["frame"] = rounds["new"][0]["frame"]
    fp32 = np.load(work / "labels_new.npy")
    for side in sides:       # labels against this tree's fp32 (the baseline's may differ in shape)
        lab = np.load(work / f"labels_{side}.npy")
        res[side]["agreement"] = float((lab == fp32).mean()) if lab.shape == fp32.shape else None
    if "int8_openvino" in sides:
        res["int8_openvino"]["agreement_int8"] = float((np.load(work / "labels_int8_openvino.npy")
                                                        == np.load(work / "labels_int8.npy")).mean())
    if "openvino" in sides:
        import openvino

        res["openvino_version"] = openvino.__version__
    if args.profile and rounds["new"][0]["profile"]:
        res["op_split"] = op_split(rounds["new"][0]["profile"])
    res["flops"] = run_child(REPO, "flops")
    res["rate"] = run_child(REPO, "rate")
    best = max(res["rate"].values())
    res["bound_s"] = res["flops"]["total"] / (best * 1e9)
    res["bound_share"] = res["bound_s"] / res["new"]["steady_s"]
    res["load_end"] = os.getloadavg()[0]
    write_report(res, args.out)
    log(f"wrote {args.out}")


def write_report(res: dict, path: Path) -> None:
    from ago_runtime.atomic import write_text

    b, n = res["base"], res["new"]
    sides = res["sides"]
    lines = [
        "# The runtime at the paper's scale (issue 39)", "",
        f"Command: `{res['command']}` ({res['date']}; load average {res['load_start']:.1f} at the "
        f"start, {res['load_end']:.1f} at the end).", "",
        f"CPU: {res.get('cpu', 'not recorded')}.", "",
        "`full` preset (1600x928 input, 200x200x16 grid, TPV 100x100x16 with the preset's widths), random weights "
        "(cost only; every voxel is called occupied, the runtime's worst case), exported without the parity check by "
        f"each side's code; frame: {res['frame']}. Baseline: commit {res['baseline']}. Best of the alternating rounds; "
        "ratios are the baseline's figure over the side's.", "",
        "| side | steady frame (s) | baseline / it | first frame (s) | bundle open (s) | planes graph alone (s) | "
        "baseline / it | peak RSS (MiB) | labels = this tree's fp32 (%) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for side in sides:
        r = res[side]
        agree = f"{100 * r['agreement']:.3f}" if r.get("agreement") is not None else "(grid differs)"
        lines.append(f"| {SIDES[side][2]} | {r['steady_s']:.2f} | {b['steady_s'] / r['steady_s']:.2f}x | "
                     f"{r['first_s']:.2f} | {r['open_s']:.2f} | {r['planes_s']:.2f} | {b['planes_s'] / r['planes_s']:.2f}x | "
                     f"{r['rss_mib']:.0f} | {agree} |")
    lines += ["", "Steady frame round by round, baseline / side: " + "; ".join(
        f"{SIDES[side][2]} " + ", ".join(f"{bs / x:.2f}x" for bs, x in zip(b["rounds_steady_s"], res[side]["rounds_steady_s"]))
        for side in sides if side != "base") + ".", "",
        f"Export: baseline {res['base_export']['export_s']:.1f} s (peak RSS {res['base_export']['export_rss_mib']:.0f} MiB), "
        f"this tree {res['new_export']['export_s']:.1f} s ({res['new_export']['export_rss_mib']:.0f} MiB)"
        + (f"; the int8 variant + {res['int8_quantise']['quantise_s']:.1f} s ({res['int8_quantise']['quantise_rss_mib']:.0f} "
           "MiB)" if "int8" in sides else "") + ".", ""]
    if "int8" in sides:
        lines += [f"int8 (`Predictor(bundle, int8=True)`: planes static QDQ with every activation range fixed to "
                  f"{tuple(res['int8_quantise']['range'])}, not calibrated; voxel stages dynamic int8; it calls "
                  f"{100 * res['int8']['occupied_share']:.1f} % occupied, fp32 {100 * n['occupied_share']:.1f} %): its "
                  "label agreement is that of an uncalibrated random-weight model, not a measure of int8 accuracy on a "
                  "trained one (benchmarks/results/int8_qat_default.md measures that on the default model).", ""]
    if "openvino" in sides:
        lines += [f"Planes graph on OpenVINO (`Predictor(bundle, device=\"openvino\"[, int8=True])`, openvino "
                  f"{res['openvino_version']}): OpenVINO's CPU device runs the planes graph, the voxel stages stay on "
                  "onnxruntime's CPU provider (ago_runtime.providers.stage_target); its planes graph alone is timed in "
                  "the Predictor's own OpenVINO session."
                  + (f" Its int8 labels agree with onnxruntime's int8 on {100 * res['int8_openvino']['agreement_int8']:.3f} "
                     "% of the voxels." if "int8_openvino" in sides else ""), ""]
    lines += [f"FLOP bound: {res['flops']['total'] / 1e9:.0f} GFLOP a frame (planes {res['flops']['planes'] / 1e9:.0f}, "
              f"{res['flops']['voxels_note']}: {res['flops']['voxels'] / 1e9:.0f}) at this CPU's best "
              f"{max(res['rate'].values()):.0f} GFLOP/s = {res['bound_s']:.2f} s; the steady frame reaches "
              f"{100 * res['bound_share']:.0f} % of it (the bound counts the main branch on every voxel; the adapted "
              f"branch on every voxel would add {res['flops']['adapted_all'] / 1e9:.0f} GFLOP; identifier "
              f"`{n['identifier']}`).", ""]
    if res.get("op_split"):
        lines += ["Where the planes graph's time goes (onnxruntime profile, this tree, share of kernel time):", "",
                  "| operator | share |", "|---|---:|"] + [f"| {op} | {s:.1f} % |" for op, s in res["op_split"]] + [""]
    write_text(path, "\n".join(lines))
    write_text(path.with_suffix(".json"), json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
