"""The real chain's models scored with the LiDAR measures a constant cannot win (issue 46), beside every no-image
baseline and the training-frame prior.

    nice -n 10 python benchmarks/real_chain_lidar_metric.py --work WORK [--out benchmarks/results/real_chain_lidar_metric.md]

WORK is the folder of a finished benchmarks/real_chain.py run (its data/, pseudo/, train/, pred_real/,
pred_synthetic/ and the JSON the run wrote, `--run-json`). For the real-trained bundle and the shipped synthetic
bundle: `ago metric --pred WORK/pred_<name> --lidar WORK/data --allow-missing --prior WORK/pseudo`
(the prior: each voxel's most frequent boxes pseudo-label over the run's training keyframes). Writes one
table: both models and every baseline on the primary measures (object ray IoU, non-ground ray IoU at
1/2/4 m, judged-voxel F1), ground ray IoU and the old measures as diagnostics, and says plainly which
baselines beat each model on which measure.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ago_runtime.atomic import write_text  # noqa: E402

MODELS = (("real", "real-trained bundle (boxes pseudo-labels)"), ("synthetic", "shipped synthetic bundle"))
PRIMARY_COLUMNS = (("object_ray_iou", "object ray IoU"), ("geometry_ray_iou_nonground@1", "non-ground @1 m"),
                   ("geometry_ray_iou_nonground@2", "non-ground @2 m"), ("geometry_ray_iou_nonground@4", "non-ground @4 m"),
                   ("voxel_f1_pct", "voxel F1"))
OTHER_COLUMNS = (("voxel_precision_pct", "voxel precision"), ("voxel_recall_pct", "voxel recall"),
                 ("geometry_ray_iou_ground@1", "ground @1 m"), ("geometry_ray_iou_ground@2", "ground @2 m"),
                 ("geometry_ray_iou_ground@4", "ground @4 m"))
DIAGNOSTIC_COLUMNS = (("depth_error_median_m", "depth error median (m)"),
                      ("lidar_hits_in_occupied_pct", "LiDAR hits in occupied (%)"),
                      ("occupied_seen_free_pct", "occupied seen free (%)"))


def cell(v) -> str:
    return "n/a" if v is None else f"{v}"


def rows_table(rows: dict[str, dict], columns) -> list[str]:
    """Markdown rows: one per predictor (name -> its measures), the given (key, label) columns."""
    lines = ["| predictor | " + " | ".join(label for _, label in columns) + " |",
             "|---|" + "---:|" * len(columns)]
    lines += [f"| {name} | " + " | ".join(cell(m[k]) for k, _ in columns) + " |" for name, m in rows.items()]
    return lines


def beaten_lines(name: str, mine: dict, baselines: dict[str, dict]) -> list[str]:
    """One line per primary measure: the baselines that score higher than `mine` in plain words, else the best
    baseline and the margin over it."""
    out = []
    for key, label in PRIMARY_COLUMNS:
        scored = {b: m[key] for b, m in baselines.items() if m[key] is not None}
        better = [f"{b} ({v})" for b, v in scored.items() if mine[key] is None or v > mine[key]]
        if better:
            out.append(f"- {name}, {label} {cell(mine[key])}: **beaten by** " + ", ".join(better))
        else:
            best = max(scored, key=scored.get)
            out.append(f"- {name}, {label} {cell(mine[key])}: no baseline beats it (best: {best} {scored[best]}, "
                       f"margin {mine[key] - scored[best]:.2f})")
    return out


def lidar_tables(summaries: dict[str, dict], labels: dict[str, str]) -> list[str]:
    """The markdown of several models' `ago metric --lidar` summaries (same frames, same baselines)."""
    first = next(iter(summaries.values()))
    baselines = {b: first["predictors"][b] for b in first["baselines"]}
    for name, s in summaries.items():
        if {b: s["predictors"][b] for b in s["baselines"]} != baselines:
            raise SystemExit(f"error: the baselines of {name} differ from the others' (not the same frames?)")
    rows = {labels[n]: s["predictors"]["prediction"] for n, s in summaries.items()}
    rows.update({f"{b} (no image)": m for b, m in baselines.items()})
    m0 = next(iter(rows.values()))
    lines = ["Primary measures (%, higher is better):", "", *rows_table(rows, PRIMARY_COLUMNS), "",
             "Also reported (voxel precision / recall over judged voxels; ground rays apart, where a flat slab is "
             "expected to do well):", "", *rows_table(rows, OTHER_COLUMNS), "",
             "Diagnostics (the first LiDAR measures, which a constant can win):", "",
             *rows_table(rows, DIAGNOSTIC_COLUMNS), "",
             f"{first['frames']} keyframes, {m0['rays']} rays: {m0['object_rays']} in an annotated box, "
             f"{m0['ground_rays']} ground (below 0.3 m in the ego frame and in no box), {m0['nonground_rays']} "
             f"non-ground; {m0['judged_occupied_voxels']} judged-occupied and {m0['judged_free_voxels']} "
             "judged-free voxels. Baselines: " + "; ".join(f"{b} = {d}" for b, d in first["baselines"].items())
             + f" (the prior over {first['prior_frames']} training keyframes' pseudo-labels).", "",
             "## Where a baseline beats the models", ""]
    for n, s in summaries.items():
        lines += beaten_lines(labels[n], s["predictors"]["prediction"], baselines)
    return lines


def run_metric(work: Path, name: str) -> tuple[dict, str]:
    """`ago metric --lidar` of WORK/pred_<name> with the training-frame prior; (its lidar summary, the command)."""
    out = work / f"lidar_metric_{name}.json"
    args = ["metric", "--pred", str(work / f"pred_{name}"), "--lidar", str(work / "data"), "--allow-missing",
            "--prior", str(work / "pseudo"), "--json", str(out)]
    r = subprocess.run([sys.executable, "-m", "ago_runtime", *args], capture_output=True, text=True,
                       env={**os.environ, "AGO_NO_PROGRESS": "1"})
    if r.returncode != 0:
        raise SystemExit(f"error: ago {' '.join(args)} failed: {r.stderr.strip().splitlines()[-1:]}")
    return json.loads(out.read_text())["lidar"], "ago " + " ".join(shlex.quote(a) for a in args)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="a finished benchmarks/real_chain.py --work folder")
    ap.add_argument("--run-json", type=Path, default=None, help="the JSON real_chain.py --json wrote for that run")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks/results/real_chain_lidar_metric.md")
    args = ap.parse_args(argv)
    for part in ("data", "pseudo", "train/config.json", "pred_real", "pred_synthetic"):
        if not (args.work / part).exists():
            raise SystemExit(f"error: {args.work / part}: missing (not a finished real_chain.py --work folder)")
    from benchmarks.run_settings import trained_settings

    t0 = time.perf_counter()
    summaries, commands = {}, []
    for name, _ in MODELS:
        summaries[name], cmd = run_metric(args.work, name)
        commands.append(cmd)
    run = json.loads(args.run_json.read_text()) if args.run_json else {}
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    load = os.getloadavg()
    me = "nice -n 10 python benchmarks/real_chain_lidar_metric.py " + " ".join(shlex.quote(str(a)) for a in
                                                                             (argv or sys.argv[1:]))
    lines = ["# The real chain's models on the LiDAR measures a constant cannot win (issue 46)", "",
             f"Command: `{me}` ({time.strftime('%Y-%m-%d')}, commit {commit}; {time.perf_counter() - t0:.0f} s on "
             f"this 2-core CPU shared with other helpers' work, load average {load[0]:.1f} / {load[1]:.1f} / "
             f"{load[2]:.1f}). It ran:", "", *[f"    {c}" for c in commands], "",
             "**These are frames the recipe has already been seen on, so this measures the metric, not "
             "generalisation.** The 11 keyframes are the last 11 of the one scene; benchmarks/results/"
             "real_chain_selected.md says what was seen of them before its selection rule was written, and they lie "
             "within ~24 m of the training keyframes in the same car park, so remembering static geometry pays.", ""]
    if run:
        lines += [f"The model: made by `{run.get('command')}` ({run.get('train_frames')} training keyframes, "
                  f"{run.get('steps')} steps, {run.get('keyframes')} keyframes superimposed per pseudo-label).",
                  f"Bundle card: `{run.get('card')}`", ""]
    lines += ["Trained with (the run's config.json where it differs from the `cpu` preset): "
              + ", ".join(f"`{t}`" for t in trained_settings(args.work / "train", "cpu")) + ".", "",
              *lidar_tables(summaries, dict(MODELS)), "",
              "Definitions and blind spots: docs/metric_and_pictures.md (\"LiDAR measures\"): space behind a return "
              "is never judged; one LiDAR sweep per keyframe (this extract has no sweeps/); object classes only from "
              "the annotated boxes.", ""]
    write_text(args.out, "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
