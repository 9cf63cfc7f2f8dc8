"""int8 against fp32 on a real scene: how many voxel labels each int8 recipe keeps (issue 52 item 2, real data).

    python -m benchmarks.int8_real_scene --checkpoint models/default/checkpoint.pt \
        --scene ../shared/data/nuscenes-scene [--readout-grid 200x200x16] [--out benchmarks/results/int8_real_scene.md]

Exports the checkpoint with `ago export --int8` (post-training: planes graph static QDQ, voxel stages dynamic)
in a temporary folder, once per recipe:

- `stem+stage8`: `--int8-float backbone.stem backbone.stage8`, calibrated on the checkpoint's training frames;
- `stem+stage8, scene-calibrated`: the same, calibrated on the scene's train split (`--calibration-data SCENE`);
- `stem+stage8+stage16`: `--int8-float backbone.stem backbone.stage8 backbone.stage16`, training frames.

Then runs every keyframe of the scene through each bundle's fp32 and int8 graphs (Predictor, the bundle's own bank
and identifier) and counts, against fp32, the voxels with the same label and the same among the voxels either
calls occupied, over all keyframes and per split (the val split, the scene's last quarter, is in no calibration).
There is no GT here: a synthetic-trained model on real images is scored only by its agreement with its own fp32.
Writes a markdown file (--out) with the command, the date and the CPU.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.int8_qat import TARGETS, agreement, commit, cpu_record

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "int8_real_scene.md"
STEM_STAGE8 = ("backbone.stem", "backbone.stage8")
RECIPES = (("stem+stage8", STEM_STAGE8, False),
           ("stem+stage8, scene-calibrated", STEM_STAGE8, True),
           ("stem+stage8+stage16", STEM_STAGE8 + ("backbone.stage16",), False))


def run(args) -> str:
    from ago_export.export import export_bundle
    from ago_runtime.formats.nuscenes import NuScenesDataset
    from ago_runtime.geometry.grid import Grid
    from ago_runtime.predict.predictor import Predictor

    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    readout = Grid.parse(args.readout_grid, "--readout-grid") if args.readout_grid else None
    ds = NuScenesDataset(args.scene, load_extras=False)
    splits = {"all": list(range(len(ds))), "val": list(ds.split("val")), "train": list(ds.split("train"))}
    rows = []
    with tempfile.TemporaryDirectory(prefix="ago-int8-real-") as tmp:
        tmp = Path(tmp)
        os.environ["AGO_CACHE_DIR"] = str(tmp / "cache")
        reference: list[np.ndarray] | None = None
        occupied_share = None
        for name, modules, scene_calibrated in RECIPES:
            out = tmp / name.replace(" ", "_").replace(",", "").replace("+", "_")
            export_bundle(args.checkpoint, out, int8=True, bank_prompts=[], readout_grid=readout,
                          log=lambda s: print(s, flush=True), int8_float=modules,
                          calibration_data=args.scene if scene_calibrated else None)
            fp32, int8 = Predictor(out), Predictor(out, int8=True)
            bank = fp32.bundle.load_bank()
            free = bank.num_classes
            if reference is None:   # every recipe's fp32 graphs are the same export of the same checkpoint
                reference = []
                for i in range(len(ds)):
                    f = ds[i]
                    reference.append(fp32.predict(f.images, f.rig, bank).semantics)
                occupied_share = float(np.mean([(r != free).mean() for r in reference]))
            labels = []
            for i in range(len(ds)):
                f = ds[i]
                labels.append(int8.predict(f.images, f.rig, bank).semantics)
                print(f"{name}: keyframe {i + 1}/{len(ds)}", flush=True)
            for split, idx in splits.items():
                same = total = same_occ = occ = 0
                for i in idx:
                    s, t, so, o = agreement(labels[i], reference[i], free)
                    same, total, same_occ, occ = same + s, total + t, same_occ + so, occ + o
                rows.append((name, split, len(idx), same / total, same_occ / max(occ, 1)))
    model, flags = cpu_record()
    lines = ["# int8 against fp32 on a real scene (issue 52 item 2, real data)", "",
             f"Command: `python -m benchmarks.int8_real_scene {' '.join(args.argv)}`  ",
             f"Run: {started}, commit {commit()}; CPU: {model}; flags of interest: {flags} (speed not measured here).  ",
             f"Scene: {args.scene} ({len(ds)} keyframes; val split: the last {len(splits['val'])}, in no calibration). "
             f"Checkpoint: {args.checkpoint}; read out on {args.readout_grid or 'the model grid'}. fp32 calls "
             f"{100 * occupied_share:.2f} % of the voxels occupied.", "",
             f"| recipe (`--int8-float`, calibration) | keyframes | labels = fp32, all voxels (>= {100 * TARGETS['all']:.1f} %) "
             f"| voxels either calls occupied (>= {100 * TARGETS['occupied']:.0f} %) |", "|---|---|---:|---:|"]
    def mark(v: float, target: float) -> str:
        return f"{100 * v:.3f} %" + (" (met)" if v >= target else " (MISSED)")

    for name, split, n, all_share, occ_share in rows:
        lines.append(f"| {name} | {split} ({n}) | {mark(all_share, TARGETS['all'])} | "
                     f"{mark(occ_share, TARGETS['occupied'])} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--readout-grid", default="200x200x16")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    args.argv = sys.argv[1:]
    text = run(args)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
