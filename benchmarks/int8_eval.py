"""int8 vs fp32 bundle: mIoU on a dataset split, argmax agreement, speed (torch-free; the runtime only).

Takes a bundle exported with `ago export --int8` and a nuScenes-layout dataset with Occ3D GT (e.g.
the synthetic city of scripts/make_default_bundle.sh). For each frame of the split: the fp32 and the
int8 Predictor (the bundle's training bank and identifier), labels brought up to the GT resolution
(nearest) and scored over mask_camera with ago_runtime.scoring.metric.OccupancyMetric (GT mapped into the
bundle's label space, Occ3D classes it does not cover ignored: as `ago eval`). Also: share of voxels
whose label agrees between int8 and fp32, and the steady-state frame time of both (median of
--reps, alternating, wall and process CPU time).

    python -m benchmarks.int8_eval --bundle B --data work/db/synth --split val
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np



def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bundle", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--out", type=Path, default=None, help="markdown file to write")
    args = ap.parse_args()
    from ago_runtime.classes import FREE, IGNORE
    from ago_runtime.scoring.metric import OccupancyMetric, upsample_nearest
    from ago_runtime.formats.nuscenes import NuScenesDataset
    from ago_runtime.predict.predictor import Predictor

    load_start = " ".join(f"{x:.2f}" for x in os.getloadavg())
    fp32, int8 = Predictor(args.bundle), Predictor(args.bundle, int8=True)
    bank = fp32.bundle.load_bank()
    K = bank.num_classes
    lut = np.full(256, IGNORE, np.uint8)
    for k, ids in enumerate(bank.occ3d_ids):
        lut[list(ids)] = k
    lut[FREE] = K
    names = list(bank.class_names) + ["free"]
    metrics = {"fp32": OccupancyMetric(names, free_index=K), "int8": OccupancyMetric(names, free_index=K)}
    ds = NuScenesDataset(args.data, load_extras=False)
    indices = ds.split(args.split)[: args.max_frames]
    agree, n_vox = 0, 0
    times = {"fp32": [], "int8": []}
    for i in indices:
        f = ds[i]
        if f.gt is None:
            raise SystemExit(f"frame {f.token} has no GT")
        x, m = fp32.prepare(f.images, f.rig)
        labels = {}
        for name, p in (("fp32", fp32), ("int8", int8)):
            labels[name] = p.predict_arrays(x, m, bank, p.bundle.identifier).semantics
        agree += int((labels["fp32"] == labels["int8"]).sum())
        n_vox += labels["fp32"].size
        gt = lut[f.gt.semantics]
        factors = tuple(int(round(g / v)) for g, v in zip(gt.shape, labels["fp32"].shape))
        for name, lab in labels.items():
            metrics[name].update(upsample_nearest(lab, factors) if factors != (1, 1, 1) else lab, gt,
                                 f.gt.mask_camera)
    f = ds[indices[0]]
    x, m = fp32.prepare(f.images, f.rig)
    for p in (fp32, int8):
        p.predict_arrays(x, m, bank)
    for _ in range(args.reps):
        for name, p in (("fp32", fp32), ("int8", int8)):
            w, c = time.perf_counter(), time.process_time()
            p.predict_arrays(x, m, bank)
            times[name].append((time.perf_counter() - w, time.process_time() - c))
    load_end = " ".join(f"{x:.2f}" for x in os.getloadavg())
    med = {k: (statistics.median(a for a, _ in v), statistics.median(b for _, b in v)) for k, v in times.items()}
    miou = {k: m.miou() * 100 for k, m in metrics.items()}
    geo = {k: m.geometry_iou() * 100 for k, m in metrics.items()}
    int8_parity = fp32.bundle.contract.variants["int8"].parity if "int8" in fp32.bundle.contract.variants else None
    L = [f"# int8 vs fp32 bundle\n",
         f"Command: `python -m benchmarks.int8_eval --bundle {args.bundle} --data {args.data} --split {args.split}`; "
         f"{len(indices)} frames; load average {load_start} -> {load_end}.  ",
         f"Bundle checkpoint: {fp32.bundle.contract.checkpoint.path} (step {fp32.bundle.contract.checkpoint.step}); "
         f"export parity: {int8_parity.frame if int8_parity else '-'}.\n",
         "| encoder | mIoU % | geometry IoU % | label agreement with fp32 | frame s (median, wall) | frame CPU s |",
         "|---|---|---|---|---|---|",
         f"| fp32 | {miou['fp32']:.2f} | {geo['fp32']:.2f} | 1 | {med['fp32'][0]:.3f} | {med['fp32'][1]:.3f} |",
         f"| int8 | {miou['int8']:.2f} | {geo['int8']:.2f} | {agree / n_vox:.4%} | {med['int8'][0]:.3f} | {med['int8'][1]:.3f} |",
         f"\nmIoU change int8 - fp32: {miou['int8'] - miou['fp32']:+.2f} points; speed fp32 / int8: "
         f"{med['fp32'][0] / med['int8'][0]:.2f}x (wall), {med['fp32'][1] / med['int8'][1]:.2f}x (CPU).  "]
    p = int8_parity
    if p:
        L.append(f"Export parity of int8 vs torch: argmax agreement main {p.agreement_main:.4%}, adapted "
                 f"{p.agreement_adapted:.4%}, identifier {p.agreement_identifier:.4%}; rel err F "
                 f"{p.rel_err_feat:.2e}, F~ {p.rel_err_feat_adapted:.2e}.")
    text = "\n".join(L) + "\n"
    if args.out:
        from ago_runtime.atomic import write_text

        write_text(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
