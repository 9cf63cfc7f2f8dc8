"""Two bundles (the shipped default and an earlier one) on the real nuScenes scene's held-out keyframes, against
their LiDAR.

    python -m benchmarks.default_bundle_real_scene --old-bundle DIR [--bundle DIR] [--scene DIR] [--work DIR] \
        [--out benchmarks/results/default_bundle_real_scene.md]

The scene's last 11 keyframes (the frames benchmarks/real_chain.py tests on) and its last 8 (scripts/train_real.sh's
test keyframes), by timestamp: `ago infer --sample T ... --picture none` of each bundle, then `ago metric --lidar`
(benchmarks/train_real.py's predict_and_score). Predictions and scores stay in --work and are reused when there
(delete it to redo). The table goes into --out above a "**Reading" part written by hand, which is kept.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ago_runtime.atomic import write_text  # noqa: E402
from benchmarks.train_real import predict_and_score  # noqa: E402

MEASURES = (("depth_error_median_m", "depth error median (m)", "{:.3f}"), ("depth_error_mean_m", "depth error mean (m)", "{:.3f}"),
            ("lidar_hits_in_occupied_pct", "LiDAR hits in occupied (%)", "{:.2f}"),
            ("occupied_seen_free_pct", "occupied seen free (%)", "{:.2f}"),
            ("rays_no_occupied_pct", "rays meeting no occupied (%)", "{:.2f}"),
            ("object_ray_iou", "object ray IoU (%)", "{:.2f}"), ("voxel_f1_pct", "voxel F1 (%)", "{:.2f}"))
HELD_OUT = (11, 8)


def last_keyframes(scene: Path, n: int) -> list[str]:
    samples = json.loads((scene / "v1.0-mini" / "sample.json").read_text())
    return [s["token"] for s in sorted(samples, key=lambda s: s["timestamp"])[-n:]]


def cells(m: dict) -> dict[str, str]:
    out = {label: fmt.format(m[key]) for key, label, fmt in MEASURES}
    out["non-ground ray IoU @1 / 2 / 4 m"] = " / ".join(f"{m[f'geometry_ray_iou_nonground@{d}']:.2f}" for d in (1, 2, 4))
    car = m.get("object_ray_iou_per_class", {}).get("car", {})
    out["car ray IoU @1 / 2 / 4 m"] = " / ".join("n/a" if car.get(f"@{d}") is None else f"{car[f'@{d}']:.2f}"
                                                 for d in (1, 2, 4))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-bundle", type=Path, required=True, help="the bundle to compare with (e.g. a worktree's)")
    ap.add_argument("--bundle", type=Path, default=REPO / "ago_runtime" / "assets" / "default_bundle")
    ap.add_argument("--scene", type=Path, default=REPO.parent / "shared" / "data" / "nuscenes-scene")
    ap.add_argument("--work", type=Path, default=REPO / "work" / "default_bundle_real_scene")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "default_bundle_real_scene.md")
    args = ap.parse_args(argv)
    for option, path, what in (("--old-bundle", args.old_bundle, "bundle.json"), ("--bundle", args.bundle, "bundle.json"),
                               ("--scene", args.scene, "v1.0-mini/sample.json")):
        if not (path / what).is_file():
            print(f"error: {option}: {path}: no {what} there", file=sys.stderr)
            sys.exit(2)
    args.work.mkdir(parents=True, exist_ok=True)
    scored = {}
    for n in HELD_OUT:
        tokens = last_keyframes(args.scene, n)
        for name, bundle in (("previous", args.old_bundle), ("new", args.bundle)):
            m = predict_and_score(f"{name}_{n}", bundle, args.scene, tokens, None, args.work, None)
            scored[(n, name)] = cells(m["predictors"]["prediction"])
    cols = [(n, name) for n in HELD_OUT for name in ("previous", "new")]
    cmd = "python -m benchmarks.default_bundle_real_scene " + " ".join(argv if argv is not None else sys.argv[1:])
    lines = [f"Command: `{cmd}`. New: `{args.bundle}`; previous: `{args.old_bundle}`. Scene: `{args.scene}`.", "",
             "| measure | " + " | ".join(f"last {n}: {'**new**' if name == 'new' else name}" for n, name in cols) + " |",
             "|---|" + "---:|" * len(cols)]
    for label in scored[cols[0]]:
        lines.append(f"| {label} | " + " | ".join(scored[c][label] for c in cols) + " |")
    old = args.out.read_text() if args.out.is_file() else ""
    head = old.split("\nCommand: `", 1)[0] if "\nCommand: `" in old else "# Two bundles on the real nuScenes scene, against its LiDAR\n"
    reading = old[old.index("\n**Reading"):] if "\n**Reading" in old else ""
    write_text(args.out, head.rstrip() + "\n\n" + "\n".join(lines) + "\n" + reading)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
