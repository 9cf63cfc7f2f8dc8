"""What `ago infer` imports before it runs: wall time of `ago infer --help` and of importing the infer
verb module, and the ago modules each leaves loaded, for two source trees side by side.

    python benchmarks/import_time.py --before /work/main --after . --rounds 7 \
        --out benchmarks/results/import_time.md

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


def run_once(tree: Path, code: str) -> tuple[float, list[str]]:
    env = dict(os.environ, PYTHONPATH=str(tree))
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", code + LIST], env=env, capture_output=True, text=True, cwd=tree)
    wall = time.perf_counter() - t
    if r.returncode != 0:
        raise SystemExit(f"{tree}: {code!r} failed:\n{r.stderr[-2000:]}")
    return wall, json.loads(r.stderr.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, required=True)
    ap.add_argument("--after", type=Path, required=True)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    cases = {"`ago infer --help` (ago_runtime.cli.run)": HELP, "`import ago_runtime.predict.cli`": IMPORT}
    walls = {(c, t): [] for c in cases for t in trees}
    modules = {}
    for _ in range(args.rounds):
        for case, code in cases.items():
            for side, tree in trees.items():
                wall, mods = run_once(tree, code)
                walls[case, side].append(wall)
                modules[case, side] = mods
    lines = ["# Import time of the `ago infer` path", "",
             f"Command: `python benchmarks/import_time.py --before {args.before} --after {args.after} "
             f"--rounds {args.rounds}`", "",
             "Wall time of a fresh `python -c ...` process (interpreter start included), median of the rounds, "
             "the two trees alternating; the machine was shared with other jobs (2 cores), so compare the "
             "columns, not the absolute numbers.", "",
             "| what | before: s | after: s | after / before | ago modules loaded before -> after | "
             "ago_train / ago_export modules before -> after |", "|---|---|---|---|---|---|"]
    for case in cases:
        b, a = (statistics.median(walls[case, s]) for s in ("before", "after"))
        mb, ma = modules[case, "before"], modules[case, "after"]
        up = [len([m for m in mods if not m.startswith("ago_runtime")]) for mods in (mb, ma)]
        lines.append(f"| {case} | {b:.3f} | {a:.3f} | {a / b:.2f} | {len(mb)} -> {len(ma)} | {up[0]} -> {up[1]} |")
    lines += ["", "Modules the `ago infer --help` run leaves loaded after the change:", "",
              ", ".join(modules[next(iter(cases)), "after"]), ""]
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    main()
