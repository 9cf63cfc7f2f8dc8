"""`ago infer` as users meet it: this tree against an older commit's code, side by side, and against the
Predictor's steady frame of this tree (issue 52 item 5).

Each round runs, as one process each (`python -m ago_runtime.cli infer --images DATASET --bundle B --out
...`, PYTHONPATH = that tree, defaults otherwise: the full PNG, the bundle's identifier, the automatic
workers), the old tree and this tree, order alternating, then a child of this tree that times the
Predictor's steady frame (`Predictor(bundle)`, one frame at a time with every core: `predict` on frames
already decoded, after three untimed frames). The first round is preceded by one untimed run of each side
(fills each side's optimised-graph cache). Wall time is measured around the whole process (start, imports,
bundle, sessions, every frame, every file), CPU time is the child's user + sys (getrusage): on a shared
machine the wall ratio of neighbouring runs is the one a user sees, the CPU ratio is less moved by other jobs.
The labels of the two sides are compared voxel by voxel.

Set up the old code in its own checkout (detached), e.g. for e6a7c3d:

    git worktree add /tmp/e6a7c3d e6a7c3d
    python -m benchmarks.infer_speed --old-tree /tmp/e6a7c3d --label e6a7c3d

Bundles: each side's shipped default bundle unless --old-bundle / --new-bundle (an old tree that reads an older
bundle format gets its own). Dataset: --dataset DIR, else a town made here first (`ago synth --scenes 1
--frames 12 --seed 5`, ~40 s). Writes benchmarks/results/infer_speed.md (--out).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHIPPED = Path("ago_runtime/assets/default_bundle")


def steady_child(bundle: str, dataset: str, frames: int) -> dict:
    """The Predictor's steady frame in this process: min / median wall and CPU seconds of `frames` timed
    `predict` calls (cycling over the dataset's first three frames, decoded beforehand) after three untimed ones."""
    from itertools import islice

    from ago_runtime import Predictor, open_frames
    from ago_runtime.predict.bundle import Bundle

    b = Bundle.load(bundle)
    p = Predictor(b)
    bank = b.load_bank()
    inputs = list(islice(iter(open_frames(Path(dataset), None, None, b.rig)), 3))
    for f in inputs:
        p.predict(f.images, f.rig, bank)
    wall, cpu = [], []
    for i in range(frames):
        f = inputs[i % len(inputs)]
        t, c = time.perf_counter(), time.process_time()
        p.predict(f.images, f.rig, bank)
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return {"wall_min": min(wall), "wall_median": statistics.median(wall), "cpu_min": min(cpu),
            "cpu_median": statistics.median(cpu)}


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_child(cmd: list[str], tree: Path) -> tuple[float, float, str]:
    """(wall s, CPU s, stdout) of one child process with `tree` first on the path; exits on failure."""
    env = dict(os.environ, PYTHONPATH=str(tree), AGO_NO_PROGRESS="1")
    c0, t0 = _children_cpu(), time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tree)
    wall, cpu = time.perf_counter() - t0, _children_cpu() - c0
    if p.returncode:
        raise SystemExit(f"{' '.join(map(shlex.quote, cmd))} (in {tree}) failed:\n{p.stderr[-2000:]}")
    return wall, cpu, p.stdout


def infer_cmd(dataset: Path, bundle: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "ago_runtime.cli", "infer", "--images", str(dataset), "--bundle", str(bundle),
            "--out", str(out)]


def check_tree(tree: Path) -> None:
    """The child really imports `tree`'s ago_runtime (not the installed one)."""
    _, _, out = run_child([sys.executable, "-c", "import ago_runtime; print(ago_runtime.__file__)"], tree)
    if not Path(out.strip()).resolve().is_relative_to(tree.resolve()):
        raise SystemExit(f"{tree}: a child imports {out.strip()} instead of this tree's ago_runtime")


def label_agreement(a: Path, b: Path) -> tuple[float, int]:
    """Share of voxels whose `semantics` agree over the npz files both folders hold, and their count."""
    import numpy as np

    same = total = files = 0
    for f in sorted(a.glob("*.npz")):
        if (b / f.name).is_file():
            with np.load(f) as x, np.load(b / f.name) as y:
                same += int((x["semantics"] == y["semantics"]).sum())
                total += x["semantics"].size
            files += 1
    return (same / total if total else float("nan")), files


def machine() -> tuple[str, str]:
    """(CPU model, its flags) from lscpu."""
    from benchmarks.machine import cpu_model_and_flags

    model, flags = cpu_model_and_flags()
    return model, " ".join(flags) or "?"


def git_commit(tree: Path) -> str:
    head = subprocess.run(["git", "-C", str(tree), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", str(tree), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return head + (" (with uncommitted changes)" if dirty else "")


def spread(xs: list[float]) -> str:
    return f"median **{statistics.median(xs):.2f}** (min {min(xs):.2f}, max {max(xs):.2f})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old-tree", type=Path, help="a checkout of the old commit (required)")
    ap.add_argument("--label", default="", help="the old commit's name in the results (default: its short hash)")
    ap.add_argument("--old-bundle", type=Path, help="bundle the old code runs (default: the old tree's shipped one)")
    ap.add_argument("--new-bundle", type=Path, help="bundle this tree runs (default: its shipped one)")
    ap.add_argument("--dataset", type=Path, help="nuScenes-layout dataset (default: a 12-frame town made first)")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--steady-frames", type=int, default=6, help="timed Predictor frames per round")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "infer_speed.md")
    ap.add_argument("--steady", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.steady:
        print(json.dumps(steady_child(args.steady[0], args.steady[1], int(args.steady[2]))))
        return
    if not args.old_tree:
        ap.error("--old-tree is required (git worktree add /tmp/OLD OLD)")
    old_tree, new_tree = args.old_tree.resolve(), REPO
    old_bundle = (args.old_bundle or old_tree / SHIPPED).resolve()
    new_bundle = (args.new_bundle or new_tree / SHIPPED).resolve()
    label = args.label or git_commit(old_tree)
    commit = git_commit(new_tree)   # at the start: the code that runs
    for tree in (old_tree, new_tree):
        check_tree(tree)
    load0 = " ".join(f"{x:.2f}" for x in os.getloadavg())
    rows, steady = [], []
    with tempfile.TemporaryDirectory(prefix="infer_speed_") as tmp:
        tmp = Path(tmp)
        dataset = args.dataset
        if dataset is None:
            dataset = tmp / "synth12"
            print("making the 12-frame town ...", flush=True)
            run_child([sys.executable, "-m", "ago_runtime.cli", "synth", "--scenes", "1", "--frames", "12", "--seed",
                       "5", "--out", str(dataset)], new_tree)
        dataset = dataset.resolve()
        sides = {"old": (old_tree, old_bundle), "new": (new_tree, new_bundle)}
        for side, (tree, bundle) in sides.items():   # untimed: fills the optimised-graph caches
            run_child(infer_cmd(dataset, bundle, tmp / f"warm_{side}"), tree)
        agreement, files = label_agreement(tmp / "warm_old", tmp / "warm_new")
        frames = len(list((tmp / "warm_new").glob("*.npz")))
        for r in range(args.rounds):
            res = {}
            for side in (("old", "new") if r % 2 == 0 else ("new", "old")):
                tree, bundle = sides[side]
                res[side] = run_child(infer_cmd(dataset, bundle, tmp / f"{side}{r}"), tree)[:2]
            _, _, out = run_child([sys.executable, "-m", "benchmarks.infer_speed", "--steady", str(new_bundle),
                                   str(dataset), str(args.steady_frames)], new_tree)
            steady.append(json.loads(out.strip().splitlines()[-1]))
            rows.append(res)
            print(f"round {r + 1}: old {res['old'][0]:.2f} s, new {res['new'][0]:.2f} s (wall); "
                  f"steady frame {steady[-1]['wall_median']:.3f} s", flush=True)
    load1 = " ".join(f"{x:.2f}" for x in os.getloadavg())
    model, flags = machine()
    speed_wall = [r["old"][0] / r["new"][0] for r in rows]
    speed_cpu = [r["old"][1] / r["new"][1] for r in rows]
    per_frame = [r["new"][0] / frames for r in rows]
    vs_steady = [pf / s["wall_median"] for pf, s in zip(per_frame, steady)]
    argv = " ".join(shlex.quote(a) for a in sys.argv[1:])
    L = [f"# `ago infer` against {label}, side by side, and against the Predictor's steady frame\n",
         f"Command: `python -m benchmarks.infer_speed {argv}` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())})  ",
         f"New: this tree, commit {commit}, bundle `{new_bundle}`  ",
         f"Old: `{old_tree}` ({label}), bundle `{old_bundle}`  ",
         f"Dataset: {args.dataset or 'a town made by `ago synth --scenes 1 --frames 12 --seed 5`'} ({frames} frames); "
         f"`ago infer` with its defaults (full PNG, automatic workers); {args.rounds} rounds, order alternating; "
         f"steady frame: `Predictor(bundle).predict`, {args.steady_frames} timed frames per round after 3 untimed.  ",
         f"CPU: {model}, {os.cpu_count()} CPUs; load average (1, 5, 15 min) at start {load0}, at end {load1}.  ",
         f"Labels old vs new: {agreement:.6f} of the voxels agree ({files} frames).\n",
         "| round | old wall s | new wall s | old / new (wall) | old CPU s | new CPU s | old / new (CPU) "
         "| new s per frame | steady frame s (median, min) | new per frame / steady |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    for i, (r, s) in enumerate(zip(rows, steady)):
        L.append(f"| {i + 1} | {r['old'][0]:.2f} | {r['new'][0]:.2f} | {speed_wall[i]:.2f} | {r['old'][1]:.2f} | "
                 f"{r['new'][1]:.2f} | {speed_cpu[i]:.2f} | {per_frame[i]:.3f} | {s['wall_median']:.3f}, "
                 f"{s['wall_min']:.3f} | {vs_steady[i]:.2f} |")
    L += ["",
          f"- new faster than {label} (old / new wall time, > 1 = faster): {spread(speed_wall)}",
          f"- the same in CPU time (user + sys of the process): {spread(speed_cpu)}",
          f"- `ago infer`'s time per frame (whole process / {frames}) / the Predictor's steady frame (target <= 1.3): "
          f"{spread(vs_steady)}",
          "", f"CPU flags: {flags}", ""]
    from ago_runtime.atomic import write_text

    write_text(args.out, "\n".join(L))
    print("\n".join(L))


if __name__ == "__main__":
    main()
