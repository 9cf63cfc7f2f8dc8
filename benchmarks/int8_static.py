"""fp32 vs dynamic int8 vs static (QDQ) int8, side by side in one process (issue 39): speed, labels, mIoU.

Takes a bundle (default: the shipped default bundle; no checkpoint needed, the quantisers work on its ONNX
files) and a nuScenes-layout dataset with Occ3D GT (a town from `ago synth`). Makes, in a temporary folder,
copies of the bundle whose int8 files are:

- `dynamic`: today's `ago export --int8` (ago_export.quantize.quantize_encoder on planes.onnx and every
  voxels_<i>.onnx: MatMul/Gemm weights int8, activations quantised per run);
- `static`: planes.onnx quantised static QDQ (ago_export.quantize.quantize_planes_static: every convolution
  int8, calibrated on real frames), the voxel stages dynamic as above (so the row differs from `dynamic` in
  the planes graph only);
- `static-mixed`: as `static` with the backbone's first convolutions left float32 (EARLY_CONVS: the stem and
  the stride-8 stage, the convolutions whose quantisation cost the most labels in a sweep on this bundle).

Calibration frames (ago_export.calibration_frames): the export's real parity frame (the nuScenes keyframe
in ../shared, when present) plus --calibration-frames frames of the dataset's --calibration-split (by
default "train", so the frames scored below were never seen by the calibration).

For every frame of --split: each variant's labels (the Predictor, the bundle's training bank and identifier)
against fp32's (share of voxels with the same label), the planes outputs' relative error against fp32
(rms and max over the three planes), and Occ3D mIoU against the GT over mask_camera (as benchmarks/int8_eval.py).
Speed: on one frame, each variant's steady whole frame (Predictor.predict_arrays) and its planes graph alone,
the median of --reps rounds that alternate between the variants (wall and process CPU time), so a load
change on a shared machine hits every variant alike.

    python -m benchmarks.int8_static --data DIR [--bundle B] [--split val] [--calibration-frames 16]
        [--out benchmarks/results/int8_static.md]

--paper-scale (speed only): the `full` preset with random weights (as benchmarks/paper_scale.py: 1600x928
input, 200x200x16 grid), exported without the parity check; the static graphs with fixed activation ranges
(UNCALIBRATED_RANGE, not calibrated: onnxruntime's calibrator needs more memory than this machine has at this
scale, and random weights make ranges meaningless); the planes graph alone of each variant, each round
opening one variant's session at a time (one paper-scale session holds GBs), timed on the real parity frame
(else the first keyframe of ../shared's nuScenes scene). Labels are not compared.

--sweep: the label agreement of static variants (SWEEP: which convolutions stay float32, how many calibration
frames, minmax or percentile ranges) on every 4th frame of --split, with a rough planes CPU-time ratio.

    python -m benchmarks.int8_static --sweep --data DIR [--out FILE]
    python -m benchmarks.int8_static --paper-scale [--reps 2] [--bundle B (an exported random `full` bundle)]
        [--out benchmarks/results/int8_static_paper.md]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
PARITY_FRAME = REPO.parent / "shared" / "data" / "nuscenes-sample"
NUSCENES_SCENE = REPO.parent / "shared" / "data" / "nuscenes-scene"
UNCALIBRATED_RANGE = (-8.0, 8.0)   # --paper-scale: the activations' fixed range (random weights; speed only)
VARIANTS = ["fp32", "dynamic", "static", "static-mixed"]
EARLY_CONVS = ("/backbone/stem/", "/backbone/stage8.")   # node-name prefixes kept float32 in static-mixed


def early_convs(planes: Path) -> list[str]:
    """The Conv nodes of planes.onnx whose names start with EARLY_CONVS."""
    import onnx

    graph = onnx.load(str(planes)).graph
    return [n.name for n in graph.node if n.op_type == "Conv" and n.name.startswith(EARLY_CONVS)]


def variant_bundle(src: Path, dst: Path, planes: Path, stages: dict[str, Path]) -> Path:
    """A copy of bundle `src` at `dst` whose "int8" variant (bundle.json "variants") is the given files."""
    from ago_runtime.atomic import write_json
    from ago_runtime.predict.bundle import BUNDLE_JSON, Bundle
    from ago_runtime.predict.contract import FileEntry, VariantSpec

    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.int8.onnx"))
    contract = Bundle.load(src).contract
    old = contract.variants.pop("int8", None)
    for key in (old.graphs.values() if old else []):
        contract.files.pop(key)
    variant = VariantSpec("int8", "benchmark", {}, None)
    for key, path in [(contract.PLANES, planes), *stages.items()]:
        shutil.copyfile(path, dst / f"{key}.int8.onnx")
        variant.graphs[key] = f"{key}_int8"
        contract.files[variant.graphs[key]] = FileEntry.of(dst, f"{key}.int8.onnx")
    contract.variants["int8"] = variant
    write_json(dst / BUNDLE_JSON, contract.to_dict())
    return dst


def build_variants(bundle: Path, work: Path, feeds: list[dict]) -> dict[str, Path]:
    """-> variant name -> bundle folder (fp32: `bundle` itself; the others with their int8 files)."""
    from ago_export.quantize import quantize_encoder, quantize_planes_static
    from ago_runtime.predict.bundle import Bundle

    b = Bundle.load(bundle)
    planes, stages = b.encoder_graphs()
    q = work / "graphs"
    q.mkdir()
    t = time.perf_counter()
    planes_dyn = quantize_encoder(planes.path, q / "planes.dyn.onnx")
    stage_dyn = {st.spec.file: quantize_encoder(st.path, q / f"{st.spec.file}.dyn.onnx") for st in stages}
    dyn_s = time.perf_counter() - t
    t = time.perf_counter()
    planes_static = quantize_planes_static(planes.path, q / "planes.static.onnx", feeds)
    static_s = time.perf_counter() - t
    keep = early_convs(planes.path)
    planes_mixed = quantize_planes_static(planes.path, q / "planes.mixed.onnx", feeds, keep_float=keep)
    print(f"quantised: dynamic {dyn_s:.1f} s, static {static_s:.1f} s ({len(feeds)} calibration frames); "
          f"static-mixed keeps {len(keep)} convolutions float", flush=True)
    return {"fp32": bundle,
            "dynamic": variant_bundle(bundle, work / "dynamic", planes_dyn, stage_dyn),
            "static": variant_bundle(bundle, work / "static", planes_static, stage_dyn),
            "static-mixed": variant_bundle(bundle, work / "static_mixed", planes_mixed, stage_dyn)}


def rel_errors(planes: list[np.ndarray], ref: list[np.ndarray]) -> tuple[float, float]:
    """(rms, max) relative error of the three planes against fp32's: the worst plane's."""
    rms = max(float(np.sqrt(np.mean((a - b) ** 2) / np.mean(b ** 2))) for a, b in zip(planes, ref))
    worst = max(float(np.abs(a - b).max() / np.abs(b).max()) for a, b in zip(planes, ref))
    return rms, worst


def paper_scale(args) -> str:
    """The --paper-scale run (see the module doc) -> its markdown."""
    from ago_export.calibration_frames import planes_feeds, read_frames
    from ago_export.export import export_bundle
    from ago_export.quantize import quantize_encoder, quantize_planes_static
    from ago_export.testing import random_checkpoint
    from ago_runtime.cache import open_session
    from ago_runtime.predict.bundle import Bundle

    load_start = " ".join(f"{x:.2f}" for x in os.getloadavg())
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    with tempfile.TemporaryDirectory(prefix="ago-int8-paper-") as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        bundle = args.bundle
        if bundle is None:
            random_checkpoint(tmp / "full.pt", "full", prompts="cw", seed=0)
            export_bundle(tmp / "full.pt", tmp / "bundle", bank_prompts=[], parity=False, log=lambda s: None)
            bundle = tmp / "bundle"
        export_s = time.perf_counter() - t
        b = Bundle.load(bundle)
        source = PARITY_FRAME if (PARITY_FRAME / "mmdet3d_info.pkl").is_file() else NUSCENES_SCENE
        frames = read_frames(source, 1, b.rig)
        feeds = planes_feeds(frames, b.preprocess)
        planes = Path(bundle) / "planes.onnx"
        t = time.perf_counter()
        graphs = {"fp32": planes, "dynamic": quantize_encoder(planes, tmp / "planes.dyn.onnx")}
        dyn_s = time.perf_counter() - t
        t = time.perf_counter()
        # onnxruntime's calibrator runs the graph with its optimisations off: at this scale that went past the
        # memory of the machine it was tried on (see the results file), so the ranges are fixed, not calibrated
        # (random weights: only the kernels' speed is measured, and it does not depend on the ranges)
        graphs["static"] = quantize_planes_static(planes, tmp / "planes.static.onnx", feeds,
                                                  uncalibrated_range=UNCALIBRATED_RANGE)
        static_s = time.perf_counter() - t
        keep = early_convs(planes)
        graphs["static-mixed"] = quantize_planes_static(planes, tmp / "planes.mixed.onnx", feeds, keep_float=keep,
                                                        uncalibrated_range=UNCALIBRATED_RANGE)
        print(f"bundle {export_s:.0f} s; quantised: dynamic {dyn_s:.0f} s, static {static_s:.0f} s", flush=True)
        feed = feeds[0]
        times: dict[str, list] = {v: [] for v in graphs}
        for _ in range(args.reps):
            for v, path in graphs.items():
                sess = open_session(path, None)   # the runtime's session options; no cache
                sess.run(None, feed)              # first run: allocations
                w, c = time.perf_counter(), time.process_time()
                sess.run(None, feed)
                times[v].append((time.perf_counter() - w, time.process_time() - c))
                del sess
    load_end = " ".join(f"{x:.2f}" for x in os.getloadavg())
    best = {v: (min(a for a, _ in ts), min(c for _, c in ts)) for v, ts in times.items()}
    L = ["# fp32 vs dynamic int8 vs static (QDQ) int8 at the paper's scale (speed only)\n",
         f"Command: `python -m benchmarks.int8_static --paper-scale --reps {args.reps}"
         f"{f' --bundle {args.bundle}' if args.bundle else ''}` ({started}; load average {load_start} -> "
         f"{load_end}).  ",
         "`full` preset (1600x928 input, 200x200x16 grid), random weights (cost only), exported without the parity "
         f"check; static graphs with every activation range fixed to {UNCALIBRATED_RANGE} (Clip outputs [0, 6]), "
         f"not calibrated; timed on {frames[0][2]}. The planes graph "
         "alone (benchmarks/results/paper_scale.md: it is nearly the whole paper-scale frame); per variant the best "
         f"of {args.reps} rounds, each round opening one variant's session after the other.\n",
         "| variant | planes s (wall) | planes CPU s | fp32 / variant (wall) | fp32 / variant (CPU) |",
         "|---|---:|---:|---:|---:|"]
    for v in graphs:
        L.append(f"| {v} | {best[v][0]:.2f} | {best[v][1]:.2f} | {best['fp32'][0] / best[v][0]:.2f}x | "
                 f"{best['fp32'][1] / best[v][1]:.2f}x |")
    return "\n".join(L) + "\n"


SWEEP = [   # (what stays float32: node-name prefixes, "depthwise" for every grouped Conv), calibration frames, method
    ((), 4, "minmax"),
    ((), 24, "minmax"),
    ((), 4, "percentile"),
    (("/backbone/stem/",), 16, "minmax"),
    (("/backbone/stem/", "depthwise"), 16, "minmax"),
    (EARLY_CONVS, 16, "minmax"),
    ((*EARLY_CONVS, "/backbone/stage16."), 16, "minmax"),
]


def float_nodes(planes: Path, keep: tuple[str, ...]) -> list[str]:
    """Conv nodes named by `keep` (name prefixes; "depthwise": every Conv with group > 1)."""
    import onnx

    out = []
    for n in onnx.load(str(planes)).graph.node:
        grouped = any(a.name == "group" and a.i > 1 for a in n.attribute)
        if n.op_type == "Conv" and (n.name.startswith(tuple(k for k in keep if k != "depthwise"))
                                    or ("depthwise" in keep and grouped)):
            out.append(n.name)
    return out


def sweep(args) -> str:
    """--sweep: label agreement with fp32 (every 4th frame of --split) of static variants (SWEEP) -> markdown."""
    from ago_export.calibration_frames import planes_feeds, read_frames
    from ago_export.quantize import quantize_encoder, quantize_planes_static
    from ago_runtime.formats.nuscenes import NuScenesDataset
    from ago_runtime.predict.bundle import Bundle
    from ago_runtime.predict.predictor import Predictor

    os.environ["AGO_NO_ORT_CACHE"] = "1"
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    b = Bundle.load(args.bundle)
    planes, stages = b.encoder_graphs()
    fp32 = Predictor(args.bundle)
    bank = fp32.bundle.load_bank()
    identifier = fp32.bundle.identifier_for(bank)
    ds = NuScenesDataset(args.data, load_extras=False)
    indices = ds.split(args.split)[::4]
    inputs = [fp32.prepare(ds[i].images, ds[i].rig) for i in indices]
    ref = [fp32.predict_arrays(x, m, bank, identifier).semantics for x, m in inputs]
    parity = read_frames(PARITY_FRAME, 1, b.rig) if (PARITY_FRAME / "mmdet3d_info.pkl").is_file() else []
    L = ["## Sweep: what stays float32, calibration frames and method (labels only)\n",
         f"Command: `python -m benchmarks.int8_static --sweep --bundle {args.bundle} --data {args.data} --split "
         f"{args.split}` ({started}); labels compared with fp32 on {len(indices)} frames (every 4th of the split); "
         "calibration: the parity frame plus N frames of the train split; voxel stages dynamic int8 (they feed only "
         "the adapted branch). Planes CPU time: median of 3 runs each, alternating with fp32 (rough: loaded "
         "machine).\n",
         "| float32 | calibration frames | method | float Convs | labels = fp32 | planes CPU fp32 / variant |",
         "|---|---:|---|---:|---:|---:|"]
    with tempfile.TemporaryDirectory(prefix="ago-int8-sweep-") as tmp:
        tmp = Path(tmp)
        stage_dyn = {st.spec.file: quantize_encoder(st.path, tmp / f"{st.spec.file}.dyn.onnx") for st in stages}
        for k, (keep, count, method) in enumerate(SWEEP):
            frames = parity + read_frames(args.data, count, b.rig, split=args.calibration_split)
            nodes = float_nodes(planes.path, keep)
            out = quantize_planes_static(planes.path, tmp / f"planes.{k}.onnx", planes_feeds(frames, b.preprocess),
                                         keep_float=nodes, method=method)
            p = Predictor(variant_bundle(args.bundle, tmp / f"v{k}", out, stage_dyn), int8=True)
            same = np.mean([(p.predict_arrays(x, m, bank, identifier).semantics == r).mean()
                            for (x, m), r in zip(inputs, ref)])
            t: dict[str, list] = {"fp32": [], "q": []}
            for _ in range(3):
                for name, q in (("fp32", fp32), ("q", p)):
                    c = time.process_time()
                    q.encoder.plane_maps(*inputs[0])
                    t[name].append(time.process_time() - c)
            what = " + ".join(k.strip("/.").replace("backbone/", "") for k in keep) or "nothing"
            L.append(f"| {what} | {len(frames)} | {method} | {len(nodes)} | {same:.4%} | "
                     f"{statistics.median(t['fp32']) / statistics.median(t['q']):.2f}x |")
            print(L[-1], flush=True)
    return "\n".join(L) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bundle", type=Path, default=None,
                    help="default: the shipped default bundle; with --paper-scale: a random `full` bundle made here")
    ap.add_argument("--data", type=Path, default=None, help="nuScenes-layout dataset with Occ3D GT (ago synth)")
    ap.add_argument("--paper-scale", action="store_true", help="speed of the planes graph of a random `full` bundle")
    ap.add_argument("--sweep", action="store_true", help="labels of static variants (SWEEP) on a few frames")
    ap.add_argument("--split", default="val")
    ap.add_argument("--calibration-split", default="train")
    ap.add_argument("--calibration-frames", type=int, default=16)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--out", type=Path, default=None, help="markdown file to write")
    args = ap.parse_args()
    if args.paper_scale:
        emit(paper_scale(args), args.out)
        return
    if args.data is None:
        ap.error("--data is required (or --paper-scale)")
    args.bundle = args.bundle or REPO / "ago_runtime" / "assets" / "default_bundle"
    if args.sweep:
        emit(sweep(args), args.out)
        return
    from ago_export.calibration_frames import planes_feeds, read_frames
    from ago_runtime.classes import FREE, IGNORE
    from ago_runtime.formats.nuscenes import NuScenesDataset
    from ago_runtime.predict.bundle import Bundle
    from ago_runtime.predict.predictor import Predictor
    from ago_runtime.scoring.metric import OccupancyMetric, to_gt_resolution

    load_start = " ".join(f"{x:.2f}" for x in os.getloadavg())
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    b = Bundle.load(args.bundle)
    frames = []
    if (PARITY_FRAME / "mmdet3d_info.pkl").is_file():
        frames += read_frames(PARITY_FRAME, 1, b.rig)
    frames += read_frames(args.data, args.calibration_frames, b.rig, split=args.calibration_split)
    feeds = planes_feeds(frames, b.preprocess)
    with tempfile.TemporaryDirectory(prefix="ago-int8-static-") as tmp:
        dirs = build_variants(args.bundle, Path(tmp), feeds)
        os.environ["AGO_CACHE_DIR"] = str(Path(tmp) / "cache")   # every variant starts from an empty cache
        for name, d in dirs.items():     # the first opening writes the optimised graph to the cache ...
            Predictor(d, int8=name != "fp32", warm_up=False)
        # ... the second reads it, as every later `ago infer` does
        preds = {name: Predictor(d, int8=name != "fp32") for name, d in dirs.items()}
        bank = preds["fp32"].bundle.load_bank()
        identifier = preds["fp32"].bundle.identifier_for(bank)
        K = bank.num_classes
        lut = np.full(256, IGNORE, np.uint8)
        for k, ids in enumerate(bank.occ3d_ids):
            lut[list(ids)] = k
        lut[FREE] = K
        names = list(bank.class_names) + ["free"]
        metrics = {v: OccupancyMetric(names, free_index=K) for v in VARIANTS}
        agree = {v: 0 for v in VARIANTS}
        errs: dict[str, list] = {v: [] for v in VARIANTS}
        n_vox = 0
        ds = NuScenesDataset(args.data, load_extras=False)
        indices = ds.split(args.split)[: args.max_frames]
        for i in indices:
            f = ds[i]
            if f.gt is None:
                raise SystemExit(f"frame {f.token} has no GT")
            x, m = preds["fp32"].prepare(f.images, f.rig)
            ref_planes = preds["fp32"].encoder.plane_maps(x, m)
            labels = {}
            for v, p in preds.items():
                labels[v] = p.predict_arrays(x, m, bank, identifier).semantics
                errs[v].append(rel_errors(p.encoder.plane_maps(x, m), ref_planes))
                agree[v] += int((labels[v] == labels["fp32"]).sum())
            n_vox += labels["fp32"].size
            gt = lut[f.gt.semantics]
            for v, lab in labels.items():
                metrics[v].update(to_gt_resolution(lab, gt.shape, f.token), gt, f.gt.mask_camera)
        # speed: one frame, rounds alternating between the variants
        f = ds[indices[0]]
        x, m = preds["fp32"].prepare(f.images, f.rig)
        for p in preds.values():
            p.predict_arrays(x, m, bank, identifier)
        frame_t = {v: [] for v in VARIANTS}
        planes_t = {v: [] for v in VARIANTS}
        for _ in range(args.reps):
            for v, p in preds.items():
                w, c = time.perf_counter(), time.process_time()
                p.predict_arrays(x, m, bank, identifier)
                frame_t[v].append((time.perf_counter() - w, time.process_time() - c))
                w, c = time.perf_counter(), time.process_time()
                p.encoder.plane_maps(x, m)
                planes_t[v].append((time.perf_counter() - w, time.process_time() - c))
    load_end = " ".join(f"{x:.2f}" for x in os.getloadavg())

    def med(ts):
        return statistics.median(a for a, _ in ts), statistics.median(c for _, c in ts)

    fr = {v: med(frame_t[v]) for v in VARIANTS}
    pl = {v: med(planes_t[v]) for v in VARIANTS}
    miou = {v: metrics[v].miou() * 100 for v in VARIANTS}
    geo = {v: metrics[v].geometry_iou() * 100 for v in VARIANTS}
    cmd = (f"python -m benchmarks.int8_static --bundle {args.bundle} --data {args.data} --split {args.split} "
           f"--calibration-split {args.calibration_split} --calibration-frames {args.calibration_frames} "
           f"--reps {args.reps}" + (f" --max-frames {args.max_frames}" if args.max_frames else ""))
    L = ["# fp32 vs dynamic int8 vs static (QDQ) int8\n",
         f"Command: `{cmd}` ({started}; {len(indices)} frames of split {args.split!r}; grid "
         f"{'x'.join(map(str, b.grid.shape))}; load average {load_start} -> {load_end}).  ",
         f"Calibration: {len(feeds)} frames ({'; '.join(name for _, _, name in frames[:2])}"
         f"{' ...' if len(frames) > 2 else ''}).  ",
         f"Speed: one frame, median of {args.reps} rounds alternating between the variants, in one process; wall "
         "and process CPU time (2 threads' CPU time adds up); each variant's sessions read their optimised graph "
         "from a fresh cache (opened twice, as a user's later runs open them).\n",
         "| variant | planes s (wall) | planes CPU s | frame s (wall) | frame CPU s | planes rel err rms / max "
         "(worst frame) | labels = fp32 | mIoU % | geometry IoU % |",
         "|---|---:|---:|---:|---:|---|---:|---:|---:|"]
    for v in VARIANTS:
        rms = max(e[0] for e in errs[v])
        worst = max(e[1] for e in errs[v])
        L.append(f"| {v} | {pl[v][0]:.3f} | {pl[v][1]:.3f} | {fr[v][0]:.3f} | {fr[v][1]:.3f} | {rms:.4f} / "
                 f"{worst:.4f} | {agree[v] / n_vox:.4%} | {miou[v]:.2f} | {geo[v]:.2f} |")
    L.append("")
    L.append("Ratios against fp32 (wall; >1 = faster): " + "; ".join(
        f"{v}: planes {pl['fp32'][0] / pl[v][0]:.2f}x, frame {fr['fp32'][0] / fr[v][0]:.2f}x, "
        f"mIoU {miou[v] - miou['fp32']:+.2f} points" for v in VARIANTS[1:]) + ".")
    emit("\n".join(L) + "\n", args.out)


def emit(text: str, out: Path | None) -> None:
    """Print the markdown and, with --out, write it (atomically)."""
    if out:
        from ago_runtime.atomic import write_text

        write_text(out, text)
    print(text)


if __name__ == "__main__":
    main()
