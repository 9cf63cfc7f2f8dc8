"""Where one `ago infer` frame's time goes, stage by stage, for the fp32 graphs on onnxruntime and the int8 variant
(issue 52 item 2: the whole frame's ratio, and the bound the shared stages put on it).

`ago infer` over a dataset predicts two frames at once on a 2-core machine, each with one onnxruntime thread
(`Predictor(workers=2)`), so the cost that sets its speed is a frame's time on one core. This benchmark opens
one Predictor per variant the way `ago infer` does (workers=2: one thread per session), then runs each frame
through the same functions `ago infer` calls, one at a time on the calling thread (the other core idle),
variants alternating frame by frame, and times each stage:

- decode: the frame's JPEGs/PNGs read and decoded (the dataset reader; the same code for every variant);
- preprocess: `Predictor.prepare` (resize, normalise, projections);
- planes: the planes graph (`SplitEncoder.plane_maps`: onnxruntime fp32, the int8 graph on OpenVINO /
  onnxruntime, or the fp32 graph on OpenVINO: `fp32-openvino`, what OpenVINO gives without int8);
- per-voxel: the slab loop's encoder part (first activation, voxel stages, bank products);
- heads: class scores and the decision (`Predictor.predict_arrays` with the planes given);
- picture: `prediction_picture` + `save_png` (the `--picture` kind given), npz: `save_npz` of the outputs.

The table gives each stage's median ms per frame; "shared" is everything but the planes graph (the same code
and graphs in every variant). The last lines give the whole frame's ratio on one core and the planes time
each variant would need for a target ratio with the shared stages as measured. Labels of each other
variant are compared with fp32's over the same frames. `--openvino-ops` adds where the int8 planes graph's time goes
on OpenVINO (its PERF_COUNT profile, one thread, on the first frames: milliseconds per run by operator type and
kernel; what remains float32 shows as `_f32` kernels). `--onnxruntime-ops` adds the same for the fp32 planes graph on
onnxruntime (its session profile, one thread, the runtime's session options: milliseconds per run by operator type),
so the two profiles can be set side by side (e.g. what the TPV sampling costs in each variant).

    python -m benchmarks.infer_stages --bundle BUNDLE_WITH_INT8 --dataset TOWN --frames 12
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STAGES = ("decode", "preprocess", "planes", "per-voxel", "heads", "picture", "npz")
PROFILE_FRAMES = 4    # frames `--openvino-ops` / `--onnxruntime-ops` profile
VARIANTS = {"fp32": {}, "int8-openvino": {"int8": True, "device": "openvino"}, "int8-cpu": {"int8": True},
            "fp32-openvino": {"device": "openvino"}}   # fp32-openvino: what OpenVINO gives without int8


def check_inputs(bundle: str, dataset: str, variants: list[str]) -> None:
    """Everything checked before any work: one `error:` line, exit 2."""
    from ago_runtime.errors import AgoInputError
    from ago_runtime.predict.bundle import Bundle

    def fail(what: str, problem: str) -> None:
        print(f"error: {what}: {problem}", file=sys.stderr)
        sys.exit(2)

    unknown = [v for v in variants if v not in VARIANTS]
    if unknown or "fp32" not in variants:
        fail("--variants", f"choose from {', '.join(VARIANTS)} (fp32 among them), got {','.join(variants)}")
    if not Path(dataset).is_dir():
        fail("--dataset", "not a folder")
    try:
        b = Bundle.load(bundle, verify_hashes=False)
    except AgoInputError as e:
        fail("--bundle", str(e))
    if any(v.startswith("int8") for v in variants) and "int8" not in b.contract.variants:
        fail("--bundle", "has no int8 variant (export it with `ago export --int8`)")
    if any(v.endswith("-openvino") for v in variants):
        from benchmarks.paper_scale import require_openvino

        require_openvino()


def run(bundle: str, dataset: str, frames: int, picture: str, variants: list[str]) -> tuple[dict, dict, int, list]:
    """-> ({variant: {stage: [s per frame]}}, {variant: (agree all, agree occupied) vs fp32}, frames run, the first
    frames' preprocessed inputs [(images, ego2img)] (up to PROFILE_FRAMES, for `openvino_ops` / `onnxruntime_ops`))."""
    import numpy as np

    from ago_runtime.atomic import save_npz
    from ago_runtime.pictures.render import save_png
    from ago_runtime.predict.bundle import Bundle
    from ago_runtime.predict.cli import prediction_picture
    from ago_runtime.predict.frames import InputFrame, open_frames
    from ago_runtime.predict.predictor import Predictor
    from ago_runtime.progress import track

    b = Bundle.load(bundle)
    predictors = {v: Predictor(b, workers=2, warm_up=True, **VARIANTS[v]) for v in variants}
    bank = b.load_bank()
    identifier = b.identifier_for(bank)
    folded = {v: p.fold(bank) for v, p in predictors.items()}
    source = open_frames(Path(dataset), None, None, b.rig)
    count = min(frames, len(source))
    times = {v: {s: [] for s in STAGES} for v in variants}
    agree = {v: [0, 0, 0, 0] for v in variants if v != "fp32"}     # same labels, voxels, same occupied, occupied
    inputs = []
    with tempfile.TemporaryDirectory() as tmp:
        it = iter(source)
        for i in track(range(count), "frames"):
            t = time.perf_counter()
            frame = InputFrame(*next(it))
            t_decode = time.perf_counter() - t
            labels = {}
            order = variants if i % 2 == 0 else variants[::-1]
            for v in order:
                p, T = predictors[v], times[v]
                T["decode"].append(t_decode)
                t0 = time.perf_counter()
                x, m = p.prepare(frame.images, frame.rig, frame.source)
                t1 = time.perf_counter()
                if v == "fp32" and i < PROFILE_FRAMES:
                    inputs.append((x, m))
                planes = p.encoder.plane_maps(x, m)
                t2 = time.perf_counter()
                pred = p.predict_arrays(x, m, bank, identifier, folded[v], False, planes=planes)
                t3 = time.perf_counter()
                if picture != "none":
                    save_png(Path(tmp) / f"{v}.png", prediction_picture(pred, frame.images, frame.name, picture))
                t4 = time.perf_counter()
                save_npz(Path(tmp) / f"{v}.npz", compresslevel=1, run_key=np.array("k"), **pred.output_arrays())
                t5 = time.perf_counter()
                T["preprocess"].append(t1 - t0)
                T["planes"].append(t2 - t1)
                share = pred.timings["encoder"] / max(1e-12, pred.timings["encoder"] + pred.timings["heads"])
                T["per-voxel"].append((t3 - t2) * share)
                T["heads"].append((t3 - t2) * (1.0 - share))
                T["picture"].append(t4 - t3)
                T["npz"].append(t5 - t4)
                labels[v] = (pred.semantics, pred.free_index)
            ref, free = labels["fp32"]
            for v, a in agree.items():
                sem = labels[v][0]
                occ = (ref != free) | (sem != free)
                a[0] += int((sem == ref).sum()); a[1] += ref.size
                a[2] += int((sem == ref)[occ].sum()); a[3] += int(occ.sum())
    return times, {v: (a[0] / a[1], a[2] / max(1, a[3])) for v, a in agree.items()}, count, inputs


def openvino_ops(bundle: str, inputs: list, top: int = 12) -> list[tuple[str, str, float]]:
    """The int8 planes graph compiled by OpenVINO for one thread with PERF_COUNT, run on `inputs` (preprocessed
    frames, `run`'s; after one untimed run) -> [(operator type, kernel, ms per run)], the `top` largest."""
    import collections

    import openvino as ov

    from ago_runtime.predict.bundle import Bundle
    from ago_runtime.providers import Precision, openvino_target

    path = Bundle.load(bundle, verify_hashes=False).encoder_graphs("int8")[0].path
    device, config = openvino_target(Precision.FP32)
    compiled = ov.Core().compile_model(str(path), device, {**config, "INFERENCE_NUM_THREADS": 1, "PERF_COUNT": True})
    request = compiled.create_infer_request()
    request.infer({"images": inputs[0][0], "ego2img": inputs[0][1]})
    total: collections.Counter = collections.Counter()
    for x, m in inputs:
        request.infer({"images": x, "ego2img": m})
        for info in request.profiling_info:
            total[(info.node_type, info.exec_type)] += info.real_time.total_seconds() * 1e3
    return [(op, kernel, ms / len(inputs)) for (op, kernel), ms in total.most_common(top)]


def onnxruntime_ops(bundle: str, inputs: list, top: int = 12) -> list[tuple[str, float]]:
    """The fp32 planes graph in an onnxruntime session of one thread with the runtime's options and profiling on,
    run on `inputs` after one run that is not counted -> [(operator type, ms per run)], the `top` largest."""
    import collections
    import json

    import onnxruntime as ort

    from ago_runtime.cache import session_options
    from ago_runtime.predict.bundle import Bundle

    path = Bundle.load(bundle, verify_hashes=False).encoder_graphs()[0].path
    so = session_options(threads=1)
    so.inter_op_num_threads = 1
    so.enable_profiling = True
    with tempfile.TemporaryDirectory() as tmp:
        so.profile_file_prefix = str(Path(tmp) / "ort")
        session = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        names = [o.name for o in session.get_outputs()]
        for x, m in [inputs[0], *inputs]:
            session.run(names, {"images": x, "ego2img": m})
        events = json.loads(Path(session.end_profiling()).read_text())
    first_end = min(e["ts"] + e["dur"] for e in events if e.get("name") == "model_run")   # runs are sequential
    total: collections.Counter = collections.Counter()
    for e in events:   # one event per node and run; the first run's are left out
        if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time") and e["ts"] > first_end:
            total[e["args"].get("op_name", "?")] += e["dur"] / 1e3
    return [(op, ms / len(inputs)) for op, ms in total.most_common(top)]


def report(args, times: dict, agree: dict, count: int, seconds: float, ops=None, ort_ops=None) -> str:
    from benchmarks.infer_speed import git_commit
    from benchmarks.machine import cpu_model_and_flags, speed_flags

    cpu, flags = cpu_model_and_flags()
    med = {v: {s: statistics.median(T[s]) * 1e3 for s in STAGES} for v, T in times.items()}
    total = {v: sum(M.values()) for v, M in med.items()}
    shared = {v: total[v] - M["planes"] for v, M in med.items()}
    cmd = (f"python -m benchmarks.infer_stages --bundle {args.bundle} --dataset {args.dataset} --frames {args.frames} "
           f"--picture {args.picture} --variants {','.join(args.variants)}" + (" --openvino-ops" if args.openvino_ops else "")
           + (" --onnxruntime-ops" if args.onnxruntime_ops else ""))
    L = [f"Command: `{cmd}` ({seconds:.0f} s)  ",
         f"Commit: {git_commit(REPO)}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.  ",
         f"CPU: {cpu}, {os.cpu_count()} cores; flags of interest: {' '.join(speed_flags(flags)) or 'none'}.  ",
         f"{count} frames, each variant on every frame (order alternating), one onnxruntime / OpenVINO thread per "
         f"session (`ago infer`'s two-worker setting), on the calling thread; picture: {args.picture}.\n",
         "Median ms per frame on one core:\n",
         "| stage | " + " | ".join(times) + " |", "|---|" + "---:|" * len(times)]
    for s in STAGES:
        L.append(f"| {s} | " + " | ".join(f"{med[v][s]:.1f}" for v in times) + " |")
    L.append("| **shared** (all but planes) | " + " | ".join(f"{shared[v]:.1f}" for v in times) + " |")
    L.append("| **whole frame** | " + " | ".join(f"**{total[v]:.1f}**" for v in times) + " |")
    L.append("")
    for v in agree:
        need = total["fp32"] / args.target - shared[v]
        L.append(f"- {v}: whole frame on one core **{total['fp32'] / total[v]:.2f}x** fp32's (planes graph "
                 f"{med['fp32']['planes'] / med[v]['planes']:.2f}x); labels agree on {100 * agree[v][0]:.3f} % of all "
                 f"voxels, {100 * agree[v][1]:.2f} % of those either calls occupied. For {args.target:g}x with these "
                 f"shared stages its planes graph would need {need:.0f} ms "
                 + (f"({med['fp32']['planes'] / need:.2f}x fp32's)" if need > 0 else "(impossible: the shared stages "
                    "alone exceed the target)") + ".")
    if ops:
        total = sum(ms for *_, ms in ops)
        L += ["", f"The int8 planes graph on OpenVINO by operator (`--openvino-ops`: PERF_COUNT, one thread, the first "
              f"frames; the {len(ops)} largest, {total:.1f} ms per run together):", "",
              "| operator | kernel | ms per run |", "|---|---|---:|"]
        L += [f"| {op} | {kernel} | {ms:.2f} |" for op, kernel, ms in ops]
    if ort_ops:
        total = sum(ms for _, ms in ort_ops)
        L += ["", f"The fp32 planes graph on onnxruntime by operator type (`--onnxruntime-ops`: its session profile, one "
              f"thread, the first frames; the {len(ort_ops)} largest, {total:.1f} ms per run together):", "",
              "| operator | ms per run |", "|---|---:|"]
        L += [f"| {op} | {ms:.2f} |" for op, ms in ort_ops]
    return "\n".join(L) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bundle", required=True, help="a bundle exported with `ago export --int8`")
    ap.add_argument("--dataset", required=True, help="nuScenes-layout dataset")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--picture", default="full", choices=["full", "bev", "none"])
    ap.add_argument("--variants", default="fp32,int8-openvino", type=lambda s: [v for v in s.split(",") if v])
    ap.add_argument("--openvino-ops", action="store_true", help="also profile the int8 planes graph on OpenVINO "
                    "by operator")
    ap.add_argument("--onnxruntime-ops", action="store_true", help="also profile the fp32 planes graph on "
                    "onnxruntime by operator type")
    ap.add_argument("--target", type=float, default=1.3, help="the whole-frame ratio the bound is computed for")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "infer_stages.md")
    args = ap.parse_args()
    if args.frames < 1:
        print(f"error: --frames: must be at least 1, got {args.frames}", file=sys.stderr)
        sys.exit(2)
    check_inputs(args.bundle, args.dataset, args.variants + (["int8-openvino"] if args.openvino_ops else []))
    from ago_runtime.errors import AgoInputError
    from ago_runtime.outputs import check_output_file

    try:
        check_output_file(args.out, "--out")   # before any work
    except AgoInputError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    t = time.perf_counter()
    times, agree, count, inputs = run(args.bundle, args.dataset, args.frames, args.picture, args.variants)
    ops = openvino_ops(args.bundle, inputs) if args.openvino_ops else None
    ort_ops = onnxruntime_ops(args.bundle, inputs) if args.onnxruntime_ops else None
    text = report(args, times, agree, count, time.perf_counter() - t, ops, ort_ops)
    print(text)
    from ago_runtime.atomic import write_text

    title = "# Where an `ago infer` frame's time goes, stage by stage (issue 52 item 2)\n\n"
    old = args.out.read_text() if args.out.exists() else ""
    body = old[len(title):] if old.startswith(title) else old
    write_text(args.out, title + "## Run\n\n" + text + ("\n" + body if body else ""))


if __name__ == "__main__":
    main()
