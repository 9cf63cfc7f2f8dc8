"""How the frame time depends on the share of voxels the main branch calls occupied (the runtime runs the
adapter's stages and the adapted bank's product on those voxels only).

A random-weights bundle calls far more voxels occupied than a trained one (the benchmark's 200x200x16
bundle: ~all of them); real scenes have ~5-15 % occupied voxels (the trained default bundle calls 9 % of
the nuScenes keyframe occupied). To see the frame time at other shares on the same bundle and frame, the
bank's phrase embeddings are scaled by a factor (weaker phrases -> more voxels free); the labels of such a
bank mean nothing, only the share matters here. Per factor: the share, the median steady-state frame
(predict_arrays from preprocessed tensors) and its split. First row, for comparison in the same process:
the bundle's own bank with the adapted branch on EVERY voxel (the encoder's chunks + decision.decide: what
the runtime did before it ran the adapter on the occupied voxels only).

    python -m benchmarks.occupied_share --bundle BUNDLE [--scales 1,0.5,0.3] [--reps 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time
from pathlib import Path

import numpy as np


from ago_runtime.predict import decision  # noqa: E402
from ago_runtime.predict.decision import Branch, Identifier  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", required=True)
    ap.add_argument("--scales", default="1,0.5,0.3,0.2")
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args()
    from benchmarks.runtime_speed import load_frame

    from ago_runtime.predict.predictor import Predictor

    p = Predictor(args.bundle)
    images, rig, frame = load_frame(p.bundle.rig)
    x, m = p.prepare(images, rig)
    base = p.bundle.load_bank()
    planes = []
    for _ in range(args.reps):
        t = time.perf_counter()
        p.encoder.plane_maps(x, m)
        planes.append(time.perf_counter() - t)
    print(f"bundle {args.bundle}, grid {p.grid.shape}, frame {frame}, load {os.getloadavg()[0]:.2f}; "
          f"planes.onnx alone {statistics.median(planes):.3f} s\n")
    print("| phrase scale | occupied share | frame s (median) | encoder s (planes + voxel stage) | heads s |")
    print("|---|---|---|---|---|")
    folded = p.fold(base)
    every = []
    for _ in range(args.reps + 1):
        t = time.perf_counter()
        for _start, _stop, h, g in p.encoder.chunks(x, m):
            z_main = decision.class_scores(p.encoder.scores(folded.A[Branch.MAIN], h), folded.c[Branch.MAIN],
                                           folded.layout)
            z_ad = decision.class_scores(p.encoder.scores(folded.A[Branch.ADAPTED], g), folded.c[Branch.ADAPTED],
                                         folded.layout)
            decision.decide(z_main, decision.main_free(z_main, folded.num_classes), z_ad, np.arange(len(h)),
                            Identifier.MIN_ENTROPY, folded.num_classes, folded.scales)
        every.append(time.perf_counter() - t)
    print(f"| 1, adapted branch on every voxel | 100 % (computed) | {statistics.median(every[1:]):.3f} | | |")
    for scale in [float(v) for v in args.scales.split(",")]:
        bank = dataclasses.replace(base, embeddings=base.embeddings * scale)
        folded = p.fold(bank)
        p.predict_arrays(x, m, bank, Identifier.MIN_ENTROPY, folded)
        wall, enc, heads = [], [], []
        for _ in range(args.reps):
            t = time.perf_counter()
            pr = p.predict_arrays(x, m, bank, Identifier.MIN_ENTROPY, folded)
            wall.append(time.perf_counter() - t)
            enc.append(pr.timings["encoder"])
            heads.append(pr.timings["heads"])
        share = float(np.mean(pr.semantics != pr.free_index))
        med = statistics.median
        print(f"| {scale:g} | {share:.1%} | {med(wall):.3f} | {med(enc):.3f} | {med(heads):.3f} |")
    print(f"\nload average at the end {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
