"""The real chain's recipe chosen on held-out training frames, the test frames scored once (issue 35).

    nice -n 10 python benchmarks/real_chain_select.py [--data ../shared/data/nuscenes-scene] \
        [--steps 2000] [--candidates 1,3,10] [--out benchmarks/results/real_chain_selected.md]

1. Selection: for each candidate K (keyframes superimposed per pseudo-label), benchmarks/real_chain.py
   with `--cut 22,8`: boxes pseudo-labels and `ago train --config cpu` on the first 22 of the 30 training
   keyframes, `ago infer` + `ago metric --lidar` of the new and of the shipped synthetic bundle on the
   next 8 (the selection frames). The 11 test keyframes (the last 11 of the scene) are not in that
   dataroot at all.
2. The rule (SELECTION_RULE, written down before any run): pick by the selection frames only.
3. Test: the picked recipe with `--cut 30,11` (trained on all 30 training keyframes, scored on the 11
   test keyframes), run once; its outcome is reported as measured, met or missed.
Each run's own markdown (per-stage time and peak RSS) and JSON go beside the output file; a finished run
(its JSON present, same recipe) is not run again, an interrupted one resumes (real_chain.py).
`--report-only` runs nothing and writes the results file from the runs finished so far.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

from ago_runtime.atomic import write_text  # noqa: E402
from benchmarks import real_chain  # noqa: E402

SELECTION_CUT = (22, 8)   # the 30 training keyframes: first 22 to train, last 8 to select on
TEST_CUT = (30, 11)       # all 30 training keyframes to train, the 11 test keyframes to score once
SELECTION_RULE = (
    "On the 8 selection frames, a candidate passes when it beats the shipped synthetic bundle on all three "
    "target measures (depth error median lower, LiDAR hits in occupied higher, occupied seen free lower). "
    "Pick the passing candidate with the lowest depth error median. If none passes, pick the candidate that "
    "beats the synthetic bundle on the most of the three; ties -> lowest depth error median; still tied -> "
    "fewer keyframes. The picked recipe is then trained on all 30 training keyframes and the 11 test "
    "keyframes are scored once; no other recipe is run on them.")
# What had been seen of the test frames before SELECTION_RULE was written (correction, issue 46)
SEEN_BEFORE = (
    "**What was seen before the rule was written (correction, issue 46).** The 11 test keyframes are not unseen. "
    "Before this rule was written (commit ece58c4, 2026-12-05 18:34 UTC), four runs of benchmarks/real_chain.py "
    "had already been scored on these same 11 frames, trained on the 30 training keyframes (commit ba03b23, "
    "17:33 UTC; benchmarks/results/real_chain.md): keyframes 1, 3 and 10 at 2000 steps and keyframes 10 at "
    "1000 steps. Of those, keyframes 3 at 2000 steps was the one seen to beat the synthetic bundle on all three "
    "measures there, and the rule's pass criterion is exactly that. The selection frames then picked the same "
    "recipe, so the test score below repeats a result already seen on these frames; it is not a held-out test. "
    "The test keyframes also lie 3.0-24.3 m (ego positions) from the nearest training keyframe, in the same car "
    "park, so a model can score on them by remembering static geometry. And the three measures can be beaten "
    "without looking at an image (benchmarks/results/real_chain_lidar_metric.md: the no-image baselines and the "
    "training-frame prior beside the model on the measures that replace them).")


def wins_count(run: dict) -> int:
    return sum(bool(run["wins"][k]) for k in real_chain.TARGETS)


def pick(runs: dict[int, dict]) -> int:
    """The candidate K chosen by SELECTION_RULE from {K: real_chain summary on the selection frames}."""
    def median(k):
        return runs[k]["results"]["real"]["depth_error_median_m"]
    passing = [k for k in runs if runs[k]["target_met"]]
    if passing:
        return min(passing, key=lambda k: (median(k), k))
    return min(runs, key=lambda k: (-wins_count(runs[k]), median(k), k))


def finished_run(out_dir: Path, tag: str, k: int, steps: int, cut: tuple[int, int]) -> dict | None:
    """The summary JSON of a finished run of this recipe and cut, or None."""
    json_path = out_dir / f"real_chain_{tag}_kf{k}.json"
    if not json_path.is_file():
        return None
    done = json.loads(json_path.read_text())
    same = (done.get("keyframes"), done.get("steps"), done.get("train_frames"), done.get("val_frames")) == (k, steps, *cut)
    return done if same else None


def run_chain(data: str, steps: int, k: int, cut: tuple[int, int], tag: str, out_dir: Path, work_root: Path) -> dict:
    """benchmarks/real_chain.py for one recipe and cut (skipped when its JSON holds the same recipe)."""
    done = finished_run(out_dir, tag, k, steps, cut)
    if done is not None:
        print(f"== {tag} kf{k}: reusing {out_dir / f'real_chain_{tag}_kf{k}.json'}", flush=True)
        return done
    argv = ["--data", data, "--steps", str(steps), "--keyframes", str(k), "--cut", f"{cut[0]},{cut[1]}",
            "--work", str(work_root / f"real_{tag}_kf{k}"), "--out", str(out_dir / f"real_chain_{tag}_kf{k}.md"),
            "--json", str(out_dir / f"real_chain_{tag}_kf{k}.json")]
    print(f"== {tag} kf{k}: python benchmarks/real_chain.py {' '.join(shlex.quote(a) for a in argv)}", flush=True)
    return real_chain.main(argv)


def measure_row(label: str, res: dict) -> str:
    return f"| {label} | " + " | ".join(str(res[key]) for key, _, _ in real_chain.MEASURES) + " |"


def stage_rows(run: dict, label: str) -> list[str]:
    return [f"| {label} | {s['stage']} | {s['seconds']} | {s['peak_rss_mb']} | {s.get('note', '')} |"
            for s in run["stages"]]


def report(args, command: str, candidates: list[int], selection: dict[int, dict], chosen: int | None,
           test: dict | None) -> str:
    """The results file; a run not finished yet (selection candidate, pick, test) is said to be missing."""
    header = "| run | " + " | ".join(label for _, label, _ in real_chain.MEASURES) + " |"
    rule = "|---|" + "---:|" * len(real_chain.MEASURES)
    missing = [k for k in candidates if k not in selection]
    lines = [
        "# The real chain: recipe selected on held-out training frames; the test frames had been seen (issue 35)", "",
        f"Command: `{command}` ({time.strftime('%Y-%m-%d')}, this 2-core CPU shared with other engineers' "
        "work; niced; one training at a time).", "",
        f"Data: `{args.data}` (one scene, 41 keyframes). The 30 training keyframes (the default split's first 3/4) "
        f"are cut into selection-train (first {SELECTION_CUT[0]}) and selection-val (last {SELECTION_CUT[1]}); the "
        f"11 test keyframes are not in the selection runs' dataroot. Cuts are two scenes with a splits.json "
        "(benchmarks/dataroot_cut.py), so a pseudo-label never superimposes a frame of the other part. Each run: "
        "boxes pseudo-labels -> `ago train --config cpu` "
        f"({args.steps} steps) -> `ago export --readout-grid 200x200x16` -> `ago infer` -> `ago metric --lidar`, "
        "beside the shipped synthetic bundle on the same frames (benchmarks/real_chain.py).", "",
        SEEN_BEFORE, "",
    ]
    if missing or test is None:
        lines += [f"**Status: incomplete.** Selection runs finished: "
                  f"{', '.join(f'keyframes {k}' for k in candidates if k in selection) or 'none'}; not finished: "
                  f"{', '.join(f'keyframes {k}' for k in missing) or 'none'}. "
                  + ("The rule is not applied until every candidate has run, and the test frames have not been "
                     "scored. " if missing else "The test run has not finished. ")
                  + "Rerunning the command finishes the rest (finished runs are reused, interrupted ones resume).", ""]
    lines += ["## Selection rule (declared before the runs)", "", SELECTION_RULE, ""]
    if selection:
        synth_sel = next(iter(selection.values()))["results"]["synthetic"]
        lines += [f"## Selection: the {SELECTION_CUT[1]} selection frames (trained on {SELECTION_CUT[0]})", "",
                  header, rule, measure_row("shipped synthetic bundle", synth_sel),
                  *[measure_row(f"keyframes {k} ([md](real_chain_select_kf{k}.md)): beats synthetic on "
                                f"{wins_count(selection[k])}/3{', passes' if selection[k]['target_met'] else ''}",
                                selection[k]["results"]["real"]) for k in candidates if k in selection], ""]
    if chosen is not None:
        lines += [f"Picked by the rule: **keyframes {chosen}**, {args.steps} steps.", ""]
    if test is not None:
        met = test["target_met"]
        lines += [
            f"## Test: the {TEST_CUT[1]} test frames, scored once by this rule but seen before it (trained on "
            f"{TEST_CUT[0]})", "",
            header, rule, measure_row("shipped synthetic bundle", test["results"]["synthetic"]),
            measure_row(f"keyframes {chosen} ([md](real_chain_test_kf{chosen}.md))", test["results"]["real"]), "",
            f"Target (beats the synthetic bundle on depth error median, LiDAR hits in occupied and occupied seen free "
            f"on the test frames): **{'met' if met else 'missed'}** "
            f"({', '.join(('better: ' if test['wins'][k] else 'not better: ') + k for k in real_chain.TARGETS)}).", "",
            f"Bundle card of the test run: `{test['card']}`", ""]
    runs = [(f"select kf{k}", selection[k]) for k in candidates if k in selection]
    runs += [(f"test kf{chosen}", test)] if test is not None else []
    if runs:
        lines += ["## Per-stage wall time and peak RSS", "",
                  "| run | stage | wall (s) | peak RSS (MB) | note |", "|---|---|---:|---:|---|",
                  *[row for label, run in runs for row in stage_rows(run, label)], "",
                  "Wall times are from a machine shared with other engineers' work (2 cores, load 12-15 during "
                  "these runs), so they are loose; the per-run markdown files give each stage's command.", ""]
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(REPO.parent / "shared/data/nuscenes-scene"), help="nuScenes dataroot")
    ap.add_argument("--work", default=str(REPO / "work"), help="the runs' work folders go under here")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--candidates", default="1,3,10", help="keyframes per pseudo-label to choose from")
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/real_chain_selected.md"))
    ap.add_argument("--report-only", action="store_true", help="run nothing: write the results file from the "
                    "runs finished so far (an incomplete status says what is missing)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out_dir, work_root = out.parent, Path(args.work)
    candidates = [int(v) for v in args.candidates.split(",")]
    command = real_chain.threads_prefix() + "nice -n 10 python benchmarks/real_chain_select.py " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]) if a != "--report-only")
    command = command.rstrip()

    if args.report_only:
        selection = {k: r for k in candidates
                     if (r := finished_run(out_dir, "select", k, args.steps, SELECTION_CUT)) is not None}
    else:
        selection = {k: run_chain(args.data, args.steps, k, SELECTION_CUT, "select", out_dir, work_root)
                     for k in candidates}
    chosen = pick(selection) if len(selection) == len(candidates) else None
    test = None
    if chosen is not None:
        print(f"== picked keyframes={chosen} by the rule; test run", flush=True)
        test = (finished_run(out_dir, "test", chosen, args.steps, TEST_CUT) if args.report_only else
                run_chain(args.data, args.steps, chosen, TEST_CUT, "test", out_dir, work_root))
    write_text(out, report(args, command, candidates, selection, chosen, test))
    print(f"wrote {out}", flush=True)
    return {"selection": selection, "chosen": chosen, "test": test}


if __name__ == "__main__":
    main()
