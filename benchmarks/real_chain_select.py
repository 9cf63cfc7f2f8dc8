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
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

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


def run_chain(data: str, steps: int, k: int, cut: tuple[int, int], tag: str, out_dir: Path, work_root: Path) -> dict:
    """benchmarks/real_chain.py for one recipe and cut (skipped when its JSON holds the same recipe)."""
    json_path = out_dir / f"real_chain_{tag}_kf{k}.json"
    if json_path.is_file():
        done = json.loads(json_path.read_text())
        if (done.get("keyframes"), done.get("steps"), done.get("train_frames"), done.get("val_frames")) == \
                (k, steps, *cut):
            print(f"== {tag} kf{k}: reusing {json_path}", flush=True)
            return done
    argv = ["--data", data, "--steps", str(steps), "--keyframes", str(k), "--cut", f"{cut[0]},{cut[1]}",
            "--work", str(work_root / f"real_{tag}_kf{k}"), "--out", str(out_dir / f"real_chain_{tag}_kf{k}.md"),
            "--json", str(json_path)]
    print(f"== {tag} kf{k}: python benchmarks/real_chain.py {' '.join(shlex.quote(a) for a in argv)}", flush=True)
    return real_chain.main(argv)


def measure_row(label: str, res: dict) -> str:
    return f"| {label} | " + " | ".join(str(res[key]) for key, _, _ in real_chain.MEASURES) + " |"


def stage_rows(run: dict, label: str) -> list[str]:
    return [f"| {label} | {s['stage']} | {s['seconds']} | {s['peak_rss_mb']} |" for s in run["stages"]]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(REPO.parent / "shared/data/nuscenes-scene"), help="nuScenes dataroot")
    ap.add_argument("--work", default=str(REPO / "work"), help="the runs' work folders go under here")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--candidates", default="1,3,10", help="keyframes per pseudo-label to choose from")
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/real_chain_selected.md"))
    args = ap.parse_args(argv)
    out = Path(args.out)
    out_dir, work_root = out.parent, Path(args.work)
    candidates = [int(v) for v in args.candidates.split(",")]

    selection = {k: run_chain(args.data, args.steps, k, SELECTION_CUT, "select", out_dir, work_root)
                 for k in candidates}
    chosen = pick(selection)
    print(f"== picked keyframes={chosen} by the rule; test run", flush=True)
    test = run_chain(args.data, args.steps, chosen, TEST_CUT, "test", out_dir, work_root)

    header = "| run | " + " | ".join(label for _, label, _ in real_chain.MEASURES) + " |"
    rule = "|---|" + "---:|" * len(real_chain.MEASURES)
    synth_sel = selection[candidates[0]]["results"]["synthetic"]
    command = real_chain.threads_prefix() + "nice -n 10 python benchmarks/real_chain_select.py " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    met = test["target_met"]
    lines = [
        "# The real chain: recipe selected on held-out training frames, test frames scored once (issue 35)", "",
        f"Command: `{command}` ({time.strftime('%Y-%m-%d')}, this 2-core CPU shared with other engineers' "
        "work; niced; one training at a time).", "",
        f"Data: `{args.data}` (one scene, 41 keyframes). The 30 training keyframes (the default split's first 3/4) "
        f"are cut into selection-train (first {SELECTION_CUT[0]}) and selection-val (last {SELECTION_CUT[1]}); the "
        f"11 test keyframes are not in the selection runs' dataroot. Cuts are two scenes with a splits.json "
        "(benchmarks/dataroot_cut.py), so a pseudo-label never superimposes a frame of the other part. Each run: "
        "boxes pseudo-labels -> `ago train --config cpu` "
        f"({args.steps} steps) -> `ago export --readout-grid 200x200x16` -> `ago infer` -> `ago metric --lidar`, "
        "beside the shipped synthetic bundle on the same frames (benchmarks/real_chain.py).", "",
        "## Selection rule (declared before the runs)", "", SELECTION_RULE, "",
        f"## Selection: the {SELECTION_CUT[1]} selection frames (trained on {SELECTION_CUT[0]})", "",
        header, rule, measure_row("shipped synthetic bundle", synth_sel),
        *[measure_row(f"keyframes {k} ([md](real_chain_select_kf{k}.md)): beats synthetic on "
                      f"{wins_count(selection[k])}/3{', passes' if selection[k]['target_met'] else ''}",
                      selection[k]["results"]["real"]) for k in candidates], "",
        f"Picked by the rule: **keyframes {chosen}**, {args.steps} steps.", "",
        f"## Test: the {TEST_CUT[1]} test frames, scored once (trained on {TEST_CUT[0]})", "",
        header, rule, measure_row("shipped synthetic bundle", test["results"]["synthetic"]),
        measure_row(f"keyframes {chosen} ([md](real_chain_test_kf{chosen}.md))", test["results"]["real"]), "",
        f"Target (beats the synthetic bundle on depth error median, LiDAR hits in occupied and occupied seen free "
        f"on the test frames): **{'met' if met else 'missed'}** "
        f"({', '.join(('better: ' if test['wins'][k] else 'not better: ') + k for k in real_chain.TARGETS)}).", "",
        f"Bundle card of the test run: `{test['card']}`", "",
        "## Per-stage wall time and peak RSS", "",
        "| run | stage | wall (s) | peak RSS (MB) |", "|---|---|---:|---:|",
        *[row for k in candidates for row in stage_rows(selection[k], f"select kf{k}")],
        *stage_rows(test, f"test kf{chosen}"), "",
        "Wall times are from a machine shared with other engineers' work (2 cores), so they are loose; the "
        "per-run markdown files give each stage's command.", "",
    ]
    write_text(out, "\n".join(lines))
    print(f"wrote {out}", flush=True)
    return {"selection": selection, "chosen": chosen, "test": test}


if __name__ == "__main__":
    main()
