"""Speed of `ago synth` (keyframes/s, everything included: world, 6 cameras, LiDAR, Occ3D GT, JPEG/PNG/npz
writing) and the voxel share of each class in the generated GT, next to nuScenes' shares.

    python -m benchmarks.synth_speed [--scenes 2] [--frames 10] [--image-size 800x450] [--grid 200x200x16]

Writes benchmarks/results/synth_speed.md (with the command that produced it). Wall time depends on
what else runs on the machine: the load average and the CPU time of this process are reported too.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


from ago_runtime.classes import FREE, OCC3D_CLASSES, NUM_SEMANTIC  # noqa: E402
from ago_runtime.formats.occ3d import Occ3DLabels  # noqa: E402
from ago_train.synth.config import SynthConfig, parse_size  # noqa: E402
from ago_train.synth.generate import write_dataset  # noqa: E402

# Reference: occupied-voxel counts per class of nuScenes occupancy GT as published with SurroundOcc /
# OpenOccupancy code (`nusc_class_frequencies`, no "others" class); Occ3D-nuScenes has similar shares.
NUSC_REFERENCE = {
    "barrier": 9.30510600e06, "bicycle": 1.41351000e05, "bus": 4.60476000e06, "car": 3.81042190e07,
    "construction_vehicle": 1.51441400e06, "motorcycle": 4.27391000e05, "pedestrian": 2.31472700e06,
    "traffic_cone": 7.36239000e05, "trailer": 4.90751100e06, "truck": 1.58413840e07,
    "driveable_surface": 3.16958899e08, "other_flat": 8.55921600e06, "sidewalk": 7.01974610e07,
    "terrain": 7.02897300e07, "manmade": 1.78178063e08, "vegetation": 1.22581273e08,
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--image-size", default="800x450")
    ap.add_argument("--grid", default="200x200x16")
    ap.add_argument("--out", default=None, help="dataset folder (default: a temporary one, deleted)")
    ap.add_argument("--results", default=str(Path(__file__).resolve().parent / "results" / "synth_speed.md"))
    args = ap.parse_args()
    w, h = parse_size(args.image_size, 2, "--image-size")
    config = SynthConfig(seed=args.seed, num_scenes=args.scenes, frames_per_scene=args.frames, image_width=w,
                         image_height=h, grid_shape=parse_size(args.grid, 3, "--grid"))
    os.environ.setdefault("AGO_NO_PROGRESS", "1")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out) if args.out else Path(tmp) / "synth"
        load0 = os.getloadavg()
        wall0, cpu0 = time.perf_counter(), time.process_time()
        summary = write_dataset(config, out, progress=False)
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        load1 = os.getloadavg()
        counts = np.zeros(FREE + 1, np.int64)
        counts_cam = np.zeros(FREE + 1, np.int64)
        lidar_obs = cam_obs = total = 0
        for f in sorted(out.glob("gts/*/*/labels.npz")):
            gt = Occ3DLabels.load(f)
            counts += np.bincount(gt.semantics.ravel(), minlength=FREE + 1)
            counts_cam += np.bincount(gt.semantics[gt.mask_camera.astype(bool)], minlength=FREE + 1)
            lidar_obs += int(gt.mask_lidar.sum())
            cam_obs += int(gt.mask_camera.sum())
            total += gt.semantics.size
        size_mb = sum(p.stat().st_size for p in out.rglob("*") if p.is_file()) / 1e6
    n = summary["samples"]
    occ = counts[:NUM_SEMANTIC].sum()
    occ_cam = counts_cam[:NUM_SEMANTIC].sum()
    ref_total = sum(NUSC_REFERENCE.values())
    command = "python -m benchmarks.synth_speed " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    lines = [
        "# `ago synth` speed and class frequencies", "",
        f"Command: `{command.strip()}`", "",
        f"- config: {args.scenes} scenes x {args.frames} keyframes, images {w}x{h} (6 cameras), grid "
        f"{config.grid_shape}, LiDAR {config.lidar_beams} x {config.lidar_azimuth_steps} rays, seed {args.seed}",
        f"- machine: {os.cpu_count()} CPUs, load average {load0[0]:.1f} before / {load1[0]:.1f} after "
        "(other jobs share the machine)",
        f"- **{n / wall:.3f} keyframes/s wall** ({wall:.1f} s for {n} keyframes, everything included: world "
        "building, rendering, LiDAR, GT, JPEG/PNG/npz writing, tables)",
        f"- CPU time of this process: {cpu:.1f} s = {cpu / n:.2f} s per keyframe "
        f"(= {n / cpu:.3f} keyframes per CPU-second, the speed on an otherwise idle core)",
        f"- dataset size {size_mb:.1f} MB; {summary['annotations'] / n:.1f} boxes and "
        f"{summary['lidar_points'] / n:.0f} LiDAR points per keyframe",
        f"- observed voxels: mask_lidar {lidar_obs / total:.1%}, mask_camera {cam_obs / total:.1%} of the grid; "
        f"occupied {occ / total:.1%}",
        "", "## Class shares of occupied voxels (GT over all generated keyframes)", "",
        "| class | synth, all voxels | synth, mask_camera | nuScenes occupancy reference |",
        "|---|---:|---:|---:|",
    ]
    for c in range(NUM_SEMANTIC):
        name = OCC3D_CLASSES[c]
        ref = NUSC_REFERENCE.get(name)
        ref_s = f"{100 * ref / ref_total:.2f} %" if ref is not None else "n/a"
        lines.append(f"| {name} | {100 * counts[c] / occ:.2f} % | {100 * counts_cam[c] / max(occ_cam, 1):.2f} % | {ref_s} |")
    lines += ["", "Reference: per-class occupied-voxel counts of nuScenes occupancy GT as shipped in public "
              "occupancy code (`nusc_class_frequencies`, SurroundOcc/OpenOccupancy; no `others` class). "
              "Occ3D-nuScenes shares are similar in ranking.", ""]
    Path(args.results).parent.mkdir(parents=True, exist_ok=True)
    Path(args.results).write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
