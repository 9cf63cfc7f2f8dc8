"""The cpu recipe on a 0.8 m tall grid (100x100x8) against a 0.4 m tall one (100x100x16), side by side.

    python -m benchmarks.grid_height --data TOWN --pseudo8 P8 --pseudo16 P16 [--pseudo16-grazing P16G] \
        --work DIR [--steps 1000] [--out benchmarks/results/grid_height.md]

P8 / P16 are `ago pseudo-labels --data TOWN --prompts cw --split train --segmenter sim --embedder sim
--keyframes 10 --interval 1 --grid 100x100x8 | 100x100x16` of the same town. Each arm is `ago train --config cpu`
(the trainer's own loop and schedule) for --steps steps with snapshots at a quarter, half and the end, the model
grid set to its pseudo-labels' grid and nothing else changed; each snapshot is scored on the town's val split by
`ago eval --readout gt` (TPV planes read at the GT's 200x200x16 voxel centres, the way the default bundle ships).
P16G (optional third arm): the same as P16 with `--carve grazing` (rays descending to the ground stop before
skimming it: far ground is left unknown instead of carved free; benchmarks/results/pseudo_far_ground.md).
Resumes: a finished arm's run and scores are reused (the same commands and settings).

Why: on the Occ3D range (z from -1.0 m) a 0.8 m layer spans z -0.2 .. 0.6 m, so a 0.8 m model puts the road in
both 0.4 m layers it covers, while the GT's ground is one 0.4 m layer (z -0.2 .. 0.2 m); default_bundle_towns'
height breakdown shows where that leaves the wrong occupied voxels.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

from benchmarks.learning_curve import occupancy_ratio  # noqa: E402  (predicted / GT occupied voxels)


def run_ago(*args: str, log: Path) -> None:
    with open(log, "a") as f:
        r = subprocess.run([sys.executable, "-m", "ago_runtime", *map(str, args)], stdout=f, stderr=subprocess.STDOUT,
                           env={**os.environ, "AGO_NO_PROGRESS": "1"})
    if r.returncode != 0:
        raise SystemExit(f"ago {args[0]} failed; see {log}")


def grid_json(shape: str) -> str:
    """`--set model.grid=` value of an XxYxZ grid over the Occ3D range."""
    from ago_runtime.geometry.grid import Grid

    return json.dumps(Grid.parse(shape).to_dict())


def arm(name: str, shape: str, data: str, pseudo: str, work: Path, steps: int) -> dict[int, dict]:
    """Train one arm (reused when its last snapshot is there) and score its snapshots on val (read out on the GT grid)."""
    snaps = sorted({steps // 4, steps // 2, steps})
    run = work / f"run_{name}"
    if not (run / "snapshots" / f"step_{steps:06d}.pt").is_file():
        resume = ["--resume"] if (run / "last.pt").is_file() else []
        run_ago("train", "--config", "cpu", "--data", data, "--pseudo", pseudo, "--prompts", "cw", "--out", run,
                "--set", f"max_steps={steps}", "--set", "ckpt_every=250", "--set", f"snapshot_steps={json.dumps(snaps)}",
                "--set", f"model.grid={grid_json(shape)}", *resume, log=work / f"train_{name}.log")
    scores = {}
    for st in snaps:
        ev = work / f"eval_{name}_{st}"
        if not (ev / "metrics.json").is_file():
            run_ago("eval", "--ckpt", run / "snapshots" / f"step_{st:06d}.pt", "--data", data, "--split", "val",
                    "--out", ev, "--readout", "gt", log=work / f"eval_{name}_{st}.log")
        m = json.loads((ev / "metrics.json").read_text())
        scores[st] = {"mIoU": m["mIoU"], "geometry_IoU": m["geometry_IoU"], "ratio": occupancy_ratio(m["metric"]),
                      "sec_per_step": _median_step(run)}
    return scores


def _median_step(run: Path) -> float | None:
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    t = sorted(r["sec_per_step"] for r in rows if "sec_per_step" in r)
    return t[len(t) // 2] if t else None


def no_image_baselines(data: str) -> dict[str, tuple[float, float]]:
    """(mIoU, geometry IoU) in % of the ground slab and the scene prior on the town's val split (same metric, mask)."""
    from ago_runtime.classes import OCC3D_NUSCENES
    from ago_runtime.geometry.grid import Grid
    from ago_runtime.scoring.metric import OccupancyMetric
    from benchmarks.default_bundle_towns import gt_frames, scene_prior, slab_labels

    table = OCC3D_NUSCENES
    names, free = list(table.label_names), table.free_index
    prior_labels, _ = scene_prior(Path(data), names, free)
    metrics = {k: OccupancyMetric(table=table) for k in ("ground slab", "scene prior")}
    for _, labels in gt_frames(Path(data), "val"):
        grid, mask = Grid.with_shape(labels.shape), labels.mask_camera.astype(bool)
        slab = slab_labels(labels.shape, grid.range_min, grid.voxel_size, names.index("driveable_surface"), free)
        metrics["ground slab"].update(slab, labels.semantics, mask)
        metrics["scene prior"].update(prior_labels, labels.semantics, mask)
    return {k: (100 * m.miou(), 100 * m.geometry_iou()) for k, m in metrics.items()}


def main(argv=None) -> None:
    from benchmarks.default_bundle_towns import cpu_line

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--pseudo8", required=True)
    ap.add_argument("--pseudo16", required=True)
    ap.add_argument("--pseudo16-grazing", default=None)
    ap.add_argument("--work", required=True)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/grid_height.md"))
    args = ap.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    started = time.time()
    arms = {"z16": arm("z16", "100x100x16", args.data, args.pseudo16, work, args.steps),
            "z8": arm("z8", "100x100x8", args.data, args.pseudo8, work, args.steps)}
    arm_names = [("z8", "100x100x8 (0.8 m tall)"), ("z16", "100x100x16 (0.4 m tall)")]
    if args.pseudo16_grazing:
        arms["z16g"] = arm("z16g", "100x100x16", args.data, args.pseudo16_grazing, work, args.steps)
        arm_names.append(("z16g", "100x100x16, pseudo-labels `--carve grazing`"))
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    cmd = "python -m benchmarks.grid_height " + " ".join(argv if argv is not None else sys.argv[1:])
    lines = ["# The cpu recipe on a 0.8 m tall grid against a 0.4 m tall one", "",
             f"Command: `{cmd}` (this invocation {time.time() - started:.0f} s; commit {commit}; "
             f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}).",
             f"Each arm: `ago train --config cpu --data {args.data} --prompts cw --set max_steps={args.steps} "
             f"--set ckpt_every=250 --set snapshot_steps=[...] --set model.grid=<the arm's grid>` on its own "
             "pseudo-labels (same town, same command but `--grid`); scored by `ago eval --split val --readout gt` "
             "(80 val frames of the training town, scenes never trained on; Occ3D metric over the camera mask at "
             "200x200x16). Ratio: predicted occupied / GT occupied voxels.",
             f"CPU: {cpu_line()} (the machine was shared with other work: step times are not a speed comparison).",
             "", "| model grid | step | val mIoU | val geometry IoU | occupancy ratio |", "|---|---:|---:|---:|---:|"]
    for name, shape in arm_names:
        for st, s in sorted(arms[name].items()):
            lines.append(f"| {shape} | {st} | {s['mIoU']:.2f} | {s['geometry_IoU']:.2f} | {s['ratio']:.2f} |")
    for name, (miou, geom) in no_image_baselines(args.data).items():
        what = "below z = 0.2 m" if name == "ground slab" else "each voxel's most frequent GT label of the train split"
        lines.append(f"| {name} (no image: {what}) | | {miou:.2f} | {geom:.2f} | |")
    from ago_runtime.atomic import write_text

    write_text(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
