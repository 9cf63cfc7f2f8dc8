"""Per-class IoU of closed-world (cw) pseudo-labels against the Occ3D GT of the same frames.

    python -m benchmarks.pseudo_class_iou --pseudo PSEUDO_DIR --gts DATASET/gts [--out FILE.md]

Answers "could the supervision see this class here?" for any town, e.g. a fresh town the model never
trained on (make its pseudo-labels with `ago pseudo-labels --prompts cw --split train ...` first). The
pseudo-labels must be in the cw label space (its 17 classes are the Occ3D classes in Occ3D order, free =
17). Pseudo-label voxels never observed (255) count as free, since nothing labels them. Pseudo-labels on
a coarser grid are upsampled by nearest neighbour to the GT grid; scored inside the GT camera mask.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np


from ago_runtime.atomic import write_text  # noqa: E402
from ago_runtime.classes import FREE, OCC3D_CLASSES  # noqa: E402
from ago_runtime.scoring.metric import OccupancyMetric, upsample_nearest  # noqa: E402


def pseudo_label_metric(pseudo: Path, gts: Path) -> OccupancyMetric:
    """The cw pseudo-labels of every frame in `pseudo` scored against the Occ3D GT in `gts` (camera mask;
    unobserved voxels count as free; coarser pseudo-labels upsampled by nearest neighbour)."""
    metric = OccupancyMetric(list(OCC3D_CLASSES[:FREE]) + ["free"], free_index=FREE)
    for d in sorted(Path(pseudo).glob("*/*/labels.npz")):
        with np.load(d) as z:
            sem = z["semantics"].astype(np.uint8)
        gt_path = Path(gts) / d.parent.parent.name / d.parent.name / "labels.npz"
        with np.load(gt_path) as g:
            gt, mask = g["semantics"], g["mask_camera"].astype(bool)
        sem = np.where(sem > FREE, FREE, sem)
        factor = tuple(a // b for a, b in zip(gt.shape, sem.shape))
        metric.update(upsample_nearest(sem, factor), gt, mask)
    return metric


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pseudo", required=True)
    ap.add_argument("--gts", required=True)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    names = list(OCC3D_CLASSES[:FREE]) + ["free"]
    metric = pseudo_label_metric(Path(args.pseudo), Path(args.gts))
    counts = metric.counts()
    iou = metric.iou()
    lines = ["# Pseudo-label IoU per class against the GT", "",
             "Command: `python -m benchmarks.pseudo_class_iou " + " ".join(shlex.quote(a) for a in
                                                                            (argv or sys.argv[1:])) + "`", "",
             f"{metric.frames} frames; camera mask; unobserved pseudo-label voxels count as free.", "",
             "| class | IoU (%) | GT voxels | pseudo-label voxels |", "|---|---:|---:|---:|"]
    for i, c in enumerate(names):
        v = "n/a" if np.isnan(iou[i]) else f"{100 * iou[i]:.2f}"
        lines.append(f"| {c} | {v} | {counts[c]['gt']} | {counts[c]['pred']} |")
    lines.append(f"| **mIoU** | {100 * metric.miou():.2f} | | |")
    text = "\n".join(lines) + "\n"
    if args.out:
        write_text(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
