"""What `ago infer` imports before it runs: wall time of `ago infer --help` and of importing the infer
verb module, and the ago modules each leaves loaded, for two source trees side by side.

    git archive a2187f0 ago_runtime ago_train ago_export prompts | tar -x -C /tmp/base
    python benchmarks/import_time.py --before /tmp/base --before-label "a2187f0 (git archive)" --after . \
        --rounds 7 --out benchmarks/results/import_time.md

Each measurement is a fresh `python` process with the tree first on PYTHONPATH; the rounds alternate
between the trees, so a loaded machine slows both alike. Reported: the median of the rounds.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HELP = "import sys; from ago_runtime.cli import run; run(['infer', '--help'])"
IMPORT = "import ago_runtime.predict.cli"
LIST = ("; import sys, json; print(json.dumps(sorted(m for m in sys.modules "
        "if m.split('.')[0] in ('ago_runtime', 'ago_train', 'ago_export'))), file=sys.stderr)")


def run_once(tree: Path, code: str) -> tuple[float, float, list[str]]:
    """(wall seconds of the process, seconds of imports by `python -X importtime`: the cumulative time of
    the top-level imports, the ago modules loaded)."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-X", "importtime", "-c", code + LIST], env=env, capture_output=True,
                       text=True, cwd=tree)
    wall = time.perf_counter() - t
    if r.returncode != 0:
        raise SystemExit(f"{tree}: {code!r} failed:\n{r.stderr[-2000:]}")
    lines = r.stderr.strip().splitlines()
    imports = 0
    for line in lines:   # "import time: self [us] | cumulative | imported package"; top level: no indent
        if line.startswith("import time:") and "|" in line:
            _, cumulative, name = line[len("import time:"):].split("|")
            if cumulative.strip().isdigit() and not name.startswith("  "):
                imports += int(cumulative)
    return wall, imports / 1e6, json.loads(lines[-1])


def _commit(tree: Path) -> str:
    r = subprocess.run(["git", "-C", str(tree), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return r.stdout.strip() or "?"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, required=True)
    ap.add_argument("--after", type=Path, required=True)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--before-label", default=None, help="what the before tree is (default: its git commit)")
    args = ap.parse_args()
    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    load = os.getloadavg()[0]
    cases = {"`ago infer --help` (ago_runtime.cli.run)": HELP, "`import ago_runtime.predict.cli`": IMPORT}
    walls = {(c, t): [] for c in cases for t in trees}
    imports = {(c, t): [] for c in cases for t in trees}
    modules = {}
    for _ in range(args.rounds):
        for case, code in cases.items():
            for side, tree in trees.items():
                wall, imp, mods = run_once(tree, code)
                walls[case, side].append(wall)
                imports[case, side].append(imp)
                modules[case, side] = mods
    lines = ["# Import time of the `ago infer` path", "",
             f"Command: `python benchmarks/import_time.py --before {args.before} "
             + (f"--before-label '{args.before_label}' " if args.before_label else "")
             + f"--after {args.after} --rounds {args.rounds}`", "",
             f"Trees: before = {args.before_label or str(args.before) + ' at ' + _commit(trees['before'])}, after = {args.after} at "
             f"{_commit(trees['after'])} (uncommitted changes, if any, included).", "",
             "Wall time of a fresh `python -c ...` process (interpreter start included), median of the rounds, "
             f"the two trees alternating; the machine was shared with other jobs (2 cores, load average "
             f"{load:.1f} at the start), so compare the columns, not the absolute numbers.", "",
             "`-X importtime`: the summed cumulative time of the top-level imports that `python -X importtime` "
             "reports for the same process (imports only).", "",
             "| what | wall before: s | wall after: s | after / before | -X importtime before: s | after: s | "
             "ago modules loaded before -> after | ago_train / ago_export modules before -> after |",
             "|---|---|---|---|---|---|---|---|"]
    for case in cases:
        b, a = (statistics.median(walls[case, s]) for s in ("before", "after"))
        ib, ia = (statistics.median(imports[case, s]) for s in ("before", "after"))
        mb, ma = modules[case, "before"], modules[case, "after"]
        up = [len([m for m in mods if not m.startswith("ago_runtime")]) for mods in (mb, ma)]
        lines.append(f"| {case} | {b:.3f} | {a:.3f} | {a / b:.2f} | {ib:.3f} | {ia:.3f} | {len(mb)} -> {len(ma)} "
                     f"| {up[0]} -> {up[1]} |")
    lines += ["", "Modules the `ago infer --help` run leaves loaded after the change:", "",
              ", ".join(modules[next(iter(cases)), "after"]), ""]
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    main()
