"""bf16 and int8 on this CPU through OpenVINO, beside onnxruntime (issue 52 items 4 and 2).

    python -m benchmarks.bf16_openvino [--bundle DIR] [--int8] [--every-graph] [--frames 6] [--rounds 2] \
        [--work work/bf16_openvino] [--out benchmarks/results/bf16_openvino.md]

One process, Predictors on the same bundle (default: the shipped one): `--device cpu` (onnxruntime's CPU
provider, fp32), `--device openvino --precision fp32`, `--device openvino --precision bf16` (OpenVINO's
INFERENCE_PRECISION_HINT; the convolutions and MatMuls on the CPU's AVX512-BF16 / AMX units). With OpenVINO's
CPU device the planes graph runs on OpenVINO and the voxel stages on onnxruntime (ago_runtime.providers.
stage_target). --int8 (a bundle with an int8 variant, `ago export --int8`) adds `--int8` on onnxruntime and on
OpenVINO; --every-graph adds OpenVINO fp32 with the voxel stages on OpenVINO too (stage_target replaced while
that Predictor opens: the placement the runtime does not choose, measured beside the one it does).
Frames: a synthetic town of `--frames` keyframes (`ago synth`, made once in --work), each preprocessed once. Per
frame and round the variants run one after the other, their order rotating, so a slow spell of the shared
machine weighs on all alike; timed: the planes graph alone (`encoder.plane_maps`) and the whole frame from the
preprocessed tensors (`Predictor.predict_arrays`: every graph plus the numpy heads). Labels of each variant
against onnxruntime fp32 on every voxel and on the voxels either call occupied. Records the CPU model and its
flags and the load average (`uptime`) before and after.
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
# (name, device, precision, int8, every graph on the device)
VARIANTS = (("onnxruntime fp32", "cpu", "fp32", False, False), ("OpenVINO fp32", "openvino", "fp32", False, False),
            ("OpenVINO bf16", "openvino", "bf16", False, False))
INT8_VARIANTS = (("onnxruntime int8", "cpu", "fp32", True, False), ("OpenVINO int8", "openvino", "fp32", True, False))
EVERY_GRAPH = ("OpenVINO fp32, every graph on it", "openvino", "fp32", False, True)
FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx512_bf16", "avx512_fp16", "amx_tile", "amx_bf16", "amx_int8")


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text(errors="replace").splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def make_town(work: Path, frames: int) -> Path:
    out = work / "synth"
    if not (out / "splits.json").is_file():
        r = subprocess.run([sys.executable, "-m", "ago_runtime.cli", "synth", "--out", str(out), "--scenes", "1",
                            "--frames", str(frames), "--image-size", "704x396", "--grid", "100x100x8", "--seed", "11",
                            "--val-fraction", "0"], capture_output=True, text=True,
                           env=dict(os.environ, PYTHONPATH=str(REPO), AGO_NO_PROGRESS="1"))
        if r.returncode != 0:
            sys.exit(f"ago synth failed:\n{r.stderr[-2000:]}")
    return out


def agreement(a: np.ndarray, b: np.ndarray, free: int) -> tuple[float, float]:
    """(% of all voxels with the same label, % of the voxels either calls occupied with the same label)."""
    same = a == b
    either = (a != free) | (b != free)
    return 100.0 * float(same.mean()), 100.0 * float(same[either].mean()) if either.any() else 100.0


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", default=None, help="bundle folder (default: the shipped default bundle)")
    ap.add_argument("--int8", action="store_true", help="add the bundle's int8 variant on onnxruntime and OpenVINO")
    ap.add_argument("--every-graph", action="store_true", help="add OpenVINO fp32 with the voxel stages on it too")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--rounds", type=int, default=2, help="times each variant runs each frame")
    ap.add_argument("--work", type=Path, default=Path("work/bf16_openvino"))
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "bf16_openvino.md")
    args = ap.parse_args(argv)

    from ago_runtime.atomic import write_json, write_text
    from ago_runtime.predict.bundle import resolve_bundle
    from ago_runtime.predict.frames import open_frames
    from ago_runtime.predict.predictor import Predictor
    from ago_runtime.providers import BF16_FLAGS, cpu_flags

    flags = cpu_flags()
    if not set(BF16_FLAGS) & flags:
        sys.exit(f"error: this CPU ({cpu_model()}) has none of {', '.join(BF16_FLAGS)}: nothing to measure")
    load_before = uptime()
    t0 = time.perf_counter()
    bundle = resolve_bundle(args.bundle)
    town = make_town(args.work, args.frames)
    variants = list(VARIANTS) + (list(INT8_VARIANTS) if args.int8 else []) + ([EVERY_GRAPH] if args.every_graph else [])
    opened, predictors = {}, {}
    for name, device, precision, int8, every_graph in variants:
        t = time.perf_counter()
        if every_graph:
            from ago_runtime.predict import encoder

            kept = encoder.stage_target
            encoder.stage_target = lambda d, p: (d, p)
            try:
                predictors[name] = Predictor(bundle, device=device, precision=precision)
            finally:
                encoder.stage_target = kept
        else:
            predictors[name] = Predictor(bundle, device=device, precision=precision, int8=int8)
        opened[name] = time.perf_counter() - t
    p0 = predictors[VARIANTS[0][0]]
    bank = p0.bundle.load_bank()
    identifier = p0.bundle.identifier_for(bank)
    free = bank.num_classes
    frames = [p0.prepare(f.images, f.rig, f.source) for f in open_frames(town)][: args.frames]
    order = [v[0] for v in variants]
    planes_s = {n: [] for n in order}
    frame_s = {n: [] for n in order}
    labels = {n: [] for n in order}
    k = 0
    for r in range(args.rounds):
        for i, (x, m) in enumerate(frames):
            for name in order[k % len(order):] + order[: k % len(order)]:
                p = predictors[name]
                t = time.perf_counter()
                p.encoder.plane_maps(x, m)
                planes_s[name].append(time.perf_counter() - t)
                t = time.perf_counter()
                pred = p.predict_arrays(x, m, bank, identifier)
                frame_s[name].append(time.perf_counter() - t)
                if r == 0:
                    labels[name].append(pred.semantics)
            k += 1
    load_after = uptime()
    ref = labels[VARIANTS[0][0]]
    rows = {}
    for name in order:
        agree = [agreement(a, b, free) for a, b in zip(labels[name], ref)]
        rows[name] = {"open_s": opened[name], "planes_s": statistics.median(planes_s[name]),
                      "frame_s": statistics.median(frame_s[name]),
                      "agree_all": float(np.mean([a for a, _ in agree])), "agree_all_min": min(a for a, _ in agree),
                      "agree_occupied": float(np.mean([o for _, o in agree])), "agree_occupied_min": min(o for _, o in agree),
                      "providers": predictors[name].encoder.planes.get_providers(),
                      "stage_providers": sorted({prov for ss in predictors[name].encoder.sessions.values()
                                                 for sess, _ in ss for prov in sess.get_providers()[:1]})}
    bf, f32 = labels["OpenVINO bf16"], labels["OpenVINO fp32"]
    bf_vs_ov = [agreement(a, b, free) for a, b in zip(bf, f32)]

    import onnxruntime
    import openvino

    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    cmd = "python -m benchmarks.bf16_openvino " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    base = rows[VARIANTS[0][0]]
    lines = ["# bf16 and int8 through OpenVINO beside onnxruntime (issue 52 items 4 and 2)", "",
             f"Command: `{cmd}` (commit {commit}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; onnxruntime "
             f"{onnxruntime.__version__}, openvino {openvino.__version__}).", "",
             f"CPU: {cpu_model()}, {os.cpu_count()} cores; flags: "
             f"{', '.join(f for f in FLAGS if f in flags)} (absent: {', '.join(f for f in FLAGS if f not in flags) or 'none'}).",
             f"Bundle: `{bundle}` (format {p0.bundle.contract.format_version if hasattr(p0.bundle.contract, 'format_version') else '?'}, "
             f"grid {'x'.join(map(str, p0.bundle.grid.shape))}, input {p0.bundle.preprocess.width}x{p0.bundle.preprocess.height}). "
             f"Frames: {len(frames)} keyframes of a synthetic town (`ago synth --scenes 1 --frames {args.frames} "
             f"--image-size 704x396 --seed 11`), {args.rounds} rounds, variants rotating per frame; identifier "
             f"{identifier.value if hasattr(identifier, 'value') else identifier}, the bundle's training bank "
             f"({bank.num_classes} classes).",
             f"Load: before `{load_before}`; after `{load_after}` (the run itself keeps the cores busy; a load well above "
             "the core count means other work shared the machine). Ratios measured side by side, medians.", "",
             "| variant | planes graph on | voxel stages on | session open (s) | planes graph (s, median) | whole frame (s, median) | "
             "planes vs onnxruntime | frame vs onnxruntime | labels = onnxruntime fp32, all voxels (%, mean / min) | "
             "occupied by either (%, mean / min) |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name in order:
        r = rows[name]
        lines.append(f"| {name} | {', '.join(r['providers'])} | {', '.join(r['stage_providers'])} | "
                     f"{r['open_s']:.2f} | {r['planes_s']:.3f} | {r['frame_s']:.3f} | "
                     f"{base['planes_s'] / r['planes_s']:.2f}x | {base['frame_s'] / r['frame_s']:.2f}x | "
                     f"{r['agree_all']:.3f} / {r['agree_all_min']:.3f} | {r['agree_occupied']:.2f} / {r['agree_occupied_min']:.2f} |")
    lines += ["", f"OpenVINO bf16 against OpenVINO fp32 (the same runtime, only the precision differs): labels agree on "
              f"{np.mean([a for a, _ in bf_vs_ov]):.3f} % of all voxels and {np.mean([o for _, o in bf_vs_ov]):.2f} % of "
              f"the voxels either calls occupied.", "",
              f"Total time of this run: {time.perf_counter() - t0:.0f} s.", ""]
    text = "\n".join(lines)
    write_text(args.out, text)
    write_json(args.out.with_suffix(".json"), {"command": cmd, "commit": commit, "cpu": cpu_model(),
                                               "flags": sorted(f for f in FLAGS if f in flags), "load_before": load_before,
                                               "load_after": load_after, "rows": rows,
                                               "planes_s": planes_s, "frame_s": frame_s})
    print(text)


if __name__ == "__main__":
    main()
