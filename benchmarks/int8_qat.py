"""fp32 vs post-training int8 (PTQ) vs quantisation-aware fine-tuned int8 (QAT), side by side on fresh towns (issue 52).

Takes the fp32 checkpoint and the QAT checkpoint made from it (`ago train --config RUN/config.json --set
quant=int8 --set init_from=FP32.pt ...`, ago_train/quant.py), or the bundles `ago export --int8` made of them,
and fresh towns (`ago synth` with seeds no
training used). Exports, in a temporary folder, both checkpoints with `ago export --int8` (the same recipe:
planes graph static QDQ calibrated on 16 frames of the checkpoint's training split, voxel stages dynamic;
read out on --readout-grid), then runs, in one process:

- `fp32`: the fp32 checkpoint's fp32 graphs (the reference);
- `ptq`: the fp32 checkpoint's int8 graphs (post-training quantisation only);
- `qat`: the QAT checkpoint's int8 graphs;
- `qat-fp32`: the QAT checkpoint's fp32 graphs (what the fine-tune did to the float model; for reading only).

Per town (every keyframe up to --frames): each variant's labels (Predictor, the fp32 bundle's training bank and
identifier) against fp32's: the share of all voxels with the same label, and of the voxels that either of the
two calls occupied; Occ3D mIoU against the town's GT over mask_camera (as benchmarks/int8_static.py), beside two
trivial predictors (all free; the ground slab: every voxel below z = 0.2 m driveable surface).
Speed: on the first town's first frame, each variant's planes graph alone (encoder.plane_maps) and its whole
frame (Predictor.predict_arrays: planes, voxel stages, bank scores, decision: what `ago infer` runs per frame),
--reps rounds that alternate between the variants (each session with the runtime's threads), so a load change on
the shared machine hits every variant alike; the ratios are of the median process CPU time (on a machine loaded
far beyond its cores wall time mostly measures the wait for a core); wall times are in the table too.

    python -m benchmarks.int8_qat --fp32 RUN/last.pt --qat QAT/last.pt --towns T1 T2 T3 T4 \
        [--frames 3] [--reps 7] [--readout-grid 200x200x16] [--out benchmarks/results/int8_qat.md]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
VARIANTS = ("fp32", "ptq", "qat", "qat-fp32")
TARGETS = {"all": 0.995, "occupied": 0.97, "miou_points": 0.3, "planes": 1.5, "frame": 1.3}
CPU_FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16", "amx_bf16", "amx_int8")


def cpu_record() -> tuple[str, str]:
    """(CPU model name, the int8/bf16-relevant flags it has) from lscpu."""
    from benchmarks.machine import cpu_model_and_flags

    model, flags = cpu_model_and_flags()
    return model, " ".join(f for f in CPU_FLAGS if f in flags)


def commit() -> str:
    r = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return r.stdout.strip() + (" (+ uncommitted changes)" if dirty else "")


def agreement(a: np.ndarray, ref: np.ndarray, free: int) -> tuple[int, int, int, int]:
    """(same labels, voxels, same labels among voxels either calls occupied, voxels either calls occupied)."""
    either = (a != free) | (ref != free)
    same = a == ref
    return int(same.sum()), int(same.size), int((same & either).sum()), int(either.sum())


def slab_labels(grid, class_names: list[str], free: int) -> np.ndarray:
    """The ground-slab predictor (benchmarks.default_bundle_towns.slab_labels) in the bundle's label space."""
    from benchmarks.default_bundle_towns import slab_labels as slab

    return slab(grid.shape, grid.range_min, grid.voxel_size, class_names.index("driveable_surface"), free)


def run(args) -> str:
    from ago_export.export import export_bundle
    from ago_runtime.classes import FREE, IGNORE
    from ago_runtime.formats.nuscenes import NuScenesDataset
    from ago_runtime.geometry.grid import Grid
    from ago_runtime.predict.bundle import Bundle
    from ago_runtime.predict.predictor import Predictor
    from ago_runtime.scoring.metric import OccupancyMetric, to_gt_resolution

    load_start = " ".join(f"{x:.2f}" for x in os.getloadavg())
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    readout = Grid.parse(args.readout_grid, "--readout-grid") if args.readout_grid else None
    with tempfile.TemporaryDirectory(prefix="ago-int8-qat-") as tmp:
        tmp = Path(tmp)
        os.environ["AGO_CACHE_DIR"] = str(tmp / "cache")   # every variant starts from an empty ORT cache
        bundles, parity = {}, {}
        for name, ckpt in (("fp32", args.fp32), ("qat", args.qat)):
            if ckpt.is_dir():   # a bundle `ago export --int8` made already
                variant = Bundle.load(ckpt).contract.variants.get("int8")
                bundles[name], parity[name] = ckpt, {"int8": variant.parity.to_dict() if variant and variant.parity else None}
                continue
            t = time.perf_counter()
            meta = export_bundle(ckpt, tmp / name, int8=True, bank_prompts=[],
                                 readout_grid=readout, log=lambda s: print(s, flush=True),
                                 calibration_data=args.calibration_data, int8_float=tuple(args.int8_float or ()))
            parity[name] = {"int8": (meta.get("variants") or {}).get("int8", {}).get("parity")}
            bundles[name] = tmp / name
            print(f"exported {name} in {time.perf_counter() - t:.0f} s", flush=True)
        dirs = {"fp32": (bundles["fp32"], False), "ptq": (bundles["fp32"], True), "qat": (bundles["qat"], True),
                "qat-fp32": (bundles["qat"], False)}
        for v, (d, q) in dirs.items():   # the first opening writes the optimised graphs to the cache ...
            Predictor(d, int8=q, warm_up=False)
        preds = {v: Predictor(d, int8=q) for v, (d, q) in dirs.items()}   # ... later ones read them
        ref = preds["fp32"]
        bank = ref.bundle.load_bank()
        identifier = ref.bundle.identifier_for(bank)
        K = bank.num_classes
        names = list(bank.class_names) + ["free"]
        lut = np.full(256, IGNORE, np.uint8)
        for k, ids in enumerate(bank.occ3d_ids):
            lut[list(ids)] = k
        lut[FREE] = K
        towns = []
        for town in args.towns:
            ds = NuScenesDataset(town, load_extras=False)
            metrics = {v: OccupancyMetric(names, free_index=K) for v in (*VARIANTS, "all free", "ground slab")}
            counts = {v: np.zeros(4, np.int64) for v in VARIANTS}
            indices = list(range(len(ds)))[: args.frames]
            for i in indices:
                f = ds[i]
                if f.gt is None:
                    raise SystemExit(f"{town}: frame {f.token} has no GT")
                x, m = ref.prepare(f.images, f.rig)
                labels = {v: p.predict_arrays(x, m, bank, identifier).semantics for v, p in preds.items()}
                gt = lut[f.gt.semantics]
                labels["all free"] = np.full_like(labels["fp32"], K)
                labels["ground slab"] = slab_labels(ref.bundle.grid, names, K)
                for v, lab in labels.items():
                    metrics[v].update(to_gt_resolution(lab, gt.shape, f.token), gt, f.gt.mask_camera)
                for v in VARIANTS:
                    counts[v] += agreement(labels[v], labels["fp32"], K)
                print(f"{Path(town).name} {f.token}: " + ", ".join(
                    f"{v} {counts[v][0] / counts[v][1]:.4%}" for v in VARIANTS[1:]), flush=True)
            towns.append({"town": Path(town).name, "frames": len(indices), "counts": counts,
                          "miou": {v: mt.miou() * 100 for v, mt in metrics.items()}})
        # speed: one frame, rounds alternating between the variants
        f = NuScenesDataset(args.towns[0], load_extras=False)[0]
        x, m = ref.prepare(f.images, f.rig)
        timed = ("fp32", "ptq", "qat")
        for v in timed:
            preds[v].predict_arrays(x, m, bank, identifier)
        frame_t = {v: [] for v in timed}
        planes_t = {v: [] for v in timed}
        for _ in range(args.reps):
            for v in timed:
                p = preds[v]
                w, c = time.perf_counter(), time.process_time()
                p.encoder.plane_maps(x, m)
                planes_t[v].append((time.perf_counter() - w, time.process_time() - c))
                w, c = time.perf_counter(), time.process_time()
                p.predict_arrays(x, m, bank, identifier)
                frame_t[v].append((time.perf_counter() - w, time.process_time() - c))
    load_end = " ".join(f"{x:.2f}" for x in os.getloadavg())
    return report(args, towns, planes_t, frame_t, parity, started, load_start, load_end)


def report(args, towns, planes_t, frame_t, parity, started, load_start, load_end) -> str:
    model, flags = cpu_record()
    # the median process CPU time: on a shared machine (load far above the core count) wall time mostly measures
    # the wait for a core, CPU time the work (the sessions do not spin while idle)
    pl = {v: statistics.median(c for _, c in t) for v, t in planes_t.items()}
    fr = {v: statistics.median(c for _, c in t) for v, t in frame_t.items()}
    cmd = (f"python -m benchmarks.int8_qat --fp32 {args.fp32} --qat {args.qat} --towns {' '.join(args.towns)} "
           f"--frames {args.frames} --reps {args.reps} --readout-grid {args.readout_grid}"
           + (f" --calibration-data {args.calibration_data}" if args.calibration_data else "")
           + (f" --int8-float {' '.join(args.int8_float)}" if args.int8_float else ""))
    L = ["# int8 that keeps the labels: fp32 vs post-training int8 (PTQ) vs quantisation-aware fine-tuned int8 (QAT)\n",
         f"Command: `{cmd}`  ",
         f"Run: {started}, commit {commit()}; load average {load_start} -> {load_end} (2 cores shared with other "
         "jobs: provisional timings).  ",
         f"CPU: {model}; flags of interest: {flags}.  ",
         "Both checkpoints exported with `ago export --int8` (planes graph static QDQ, per-channel int8 weights, uint8 "
         "activations calibrated on 16 frames of the checkpoint's training split; voxel stages dynamic int8"
         + (f"; the convolutions of {', '.join(args.int8_float)} kept in float32" if args.int8_float else "")
         + "); export "
         "parity of the int8 graphs vs torch on the export's parity frame: " + "; ".join(
             f"{k}: {json.dumps(p['int8'], default=str)[:300]}" for k, p in parity.items() if p.get("int8")) + ".\n",
         "## Labels against fp32, mIoU against the GT (per fresh town)\n",
         "| town | frames | variant | labels = fp32 (all voxels) | labels = fp32 (voxels either calls occupied) | "
         "mIoU % | mIoU - fp32 |",
         "|---|---:|---|---:|---:|---:|---:|"]
    for t in towns:
        for v in (*VARIANTS, "all free", "ground slab"):
            if v in t["counts"]:
                c = t["counts"][v]
                a, o = f"{c[0] / c[1]:.4%}", f"{c[2] / max(c[3], 1):.4%}"
            else:
                a = o = "-"
            L.append(f"| {t['town']} | {t['frames']} | {v} | {a} | {o} | {t['miou'][v]:.2f} | "
                     f"{t['miou'][v] - t['miou']['fp32']:+.2f} |")
    total = {v: sum(t["counts"][v] for t in towns) for v in VARIANTS}
    L += ["", "## Against the targets (issue 52 item 2)\n",
          "| variant | labels = fp32, all (>= 99.5 %) | occupied by either (>= 97 %) | worst town's mIoU change "
          "(within 0.3) | planes fp32 / variant (>= 1.5x) | frame fp32 / variant (>= 1.3x) |",
          "|---|---:|---:|---:|---:|---:|"]
    for v in ("ptq", "qat"):
        c = total[v]
        worst = max((t["miou"][v] - t["miou"]["fp32"] for t in towns), key=abs)
        checks = [c[0] / c[1] >= TARGETS["all"], c[2] / max(c[3], 1) >= TARGETS["occupied"],
                  abs(worst) <= TARGETS["miou_points"], pl["fp32"] / pl[v] >= TARGETS["planes"],
                  fr["fp32"] / fr[v] >= TARGETS["frame"]]
        vals = [f"{c[0] / c[1]:.4%}", f"{c[2] / max(c[3], 1):.4%}", f"{worst:+.2f}", f"{pl['fp32'] / pl[v]:.2f}x",
                f"{fr['fp32'] / fr[v]:.2f}x"]
        L.append(f"| {v} | " + " | ".join(f"{s} ({'met' if ok else 'MISSED'})" for s, ok in zip(vals, checks)) + " |")
    L += ["", f"Speed: the first town's first frame, {args.reps} rounds alternating between the variants; the ratios "
          "above are of the median process CPU time (2 threads' CPU time adds up). Per variant, best / median wall s and "
          "median CPU s:", "",
          "| variant | planes wall best | planes wall median | planes CPU | frame wall best | frame wall median | "
          "frame CPU |", "|---|---:|---:|---:|---:|---:|---:|"]
    for v in pl:
        L.append(f"| {v} | {min(w for w, _ in planes_t[v]):.3f} | {statistics.median(w for w, _ in planes_t[v]):.3f} | "
                 f"{pl[v]:.3f} | {min(w for w, _ in frame_t[v]):.3f} | "
                 f"{statistics.median(w for w, _ in frame_t[v]):.3f} | {fr[v]:.3f} |")
    return "\n".join(L) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fp32", type=Path, required=True,
                    help="the fp32 checkpoint (`ago train`), or its bundle made by `ago export --int8`")
    ap.add_argument("--qat", type=Path, required=True,
                    help="its QAT fine-tune (`--set quant=int8`), or its bundle made by `ago export --int8`")
    ap.add_argument("--towns", nargs="+", required=True, help="fresh towns (`ago synth`, seeds no training used)")
    ap.add_argument("--frames", type=int, default=3, help="keyframes scored per town")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--readout-grid", default="200x200x16")
    ap.add_argument("--calibration-data", type=Path, default=None,
                    help="default: each checkpoint's training data (its train split calibrates the int8 graph)")
    ap.add_argument("--int8-float", nargs="+", default=None, metavar="MODULE",
                    help="torch modules whose convolutions stay float32 in both int8 exports, as `ago export "
                    "--int8-float` (e.g. backbone.stem backbone.stage8)")
    ap.add_argument("--out", type=Path, default=None, help="markdown file to write")
    args = ap.parse_args()
    text = run(args)
    if args.out:
        from ago_runtime.atomic import write_text

        write_text(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
