"""Bundle format 4 against format 3: frame latency side by side, in one process, alternating.

    python benchmarks/bundle_format4.py [--rounds 9] [--reps 3] [--out benchmarks/results/bundle_format4.md]

Old side: the format-3 default bundle and the runtime of the commit before format 4, both taken from git
history (`git archive`; the runtime is imported as `ago_runtime_v3`, scripts/migrate_bundle_v3.py::
load_old_runtime). New side: this tree's runtime and its shipped (migrated) format-4 default bundle. Same
model, same demo frame, same preprocessed tensors. Each round times `predict_arrays` --reps times per side
and identifier, the sides alternating within the round; the figures are the median and minimum over the
rounds of each round's median. Labels are compared too (they must be identical).
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from ago_runtime.atomic import write_text  # noqa: E402
from ago_runtime.predict.contract import Identifier  # noqa: E402


def format3_tree(dest: Path) -> Path:
    gone = subprocess.run(["git", "log", "-n1", "--format=%H", "--", "ago_runtime/assets/default_bundle/voxels_1.onnx"],
                          cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()
    archive = subprocess.run(["git", "archive", f"{gone}^", "ago_runtime"], cwd=REPO, capture_output=True,
                             check=True).stdout
    dest.mkdir(parents=True)
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "bundle_format4.md")
    args = ap.parse_args(argv)

    from migrate_bundle_v3 import demo_inputs, load_old_runtime

    from ago_runtime.predict.bundle import DEFAULT_BUNDLE_DIR
    from ago_runtime.predict.predictor import Predictor

    work = Path(tempfile.mkdtemp(prefix="ago_format4_bench_"))
    try:
        old_tree = format3_tree(work / "v3")
        old_mod = load_old_runtime(old_tree, work / "import")
        old_p = old_mod.Predictor(old_tree / "ago_runtime" / "assets" / "default_bundle")
        new_p = Predictor(DEFAULT_BUNDLE_DIR)
        images, rig = demo_inputs()
        x, m = new_p.prepare(images, rig)
        sides = {"format 3 (old runtime)": (old_p, old_p.bundle.load_bank(), lambda i: i.value),
                 "format 4 (this runtime)": (new_p, new_p.bundle.load_bank(), lambda i: i)}
        identifiers = [Identifier.NONE, Identifier.MIN_ENTROPY]
        times = {(s, i): [] for s in sides for i in identifiers}
        same = {}
        load0 = os.getloadavg()
        for _round in range(args.rounds):
            for ident in identifiers:
                labels = {}
                for name, (p, bank, spell) in sides.items():
                    folded = p.fold(bank)
                    reps = []
                    for _ in range(args.reps):
                        t = time.perf_counter()
                        pred = p.predict_arrays(x, m, bank, spell(ident), folded)
                        reps.append(time.perf_counter() - t)
                    times[(name, ident)].append(statistics.median(reps))
                    labels[name] = pred.semantics
                a, b = labels.values()
                same[ident] = int(np.sum(a == b)), a.size
        load1 = os.getloadavg()
    finally:
        shutil.rmtree(work, ignore_errors=True)

    rows = []
    for ident in identifiers:
        for name in sides:
            t = times[(name, ident)]
            rows.append(f"| {ident.value} | {name} | {statistics.median(t):.3f} | {min(t):.3f} |")
    ratio = {i: statistics.median(times[(list(sides)[1], i)]) / statistics.median(times[(list(sides)[0], i)])
             for i in identifiers}
    text = f"""# Bundle format 4 against format 3: frame latency, side by side

Command: `python benchmarks/bundle_format4.py --rounds {args.rounds} --reps {args.reps}`
Model: the shipped default bundle (200x200x16 read-out grid), format 3 (from git history) and its migration
to format 4 (scripts/migrate_bundle_v3.py); the demo frame; `predict_arrays` from preprocessed tensors with
the training bank (planes, voxel stages, bank products, decision). One process, the sides alternating in
every round; per round the median of {args.reps} predictions. Load average at start {load0[0]:.2f} {load0[1]:.2f}
{load0[2]:.2f}, at end {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}: a shared, LOADED 2-core machine (other
engineers' jobs ran at the same time), so compare the sides, not the absolute seconds.

| identifier | side | s per frame, median of rounds | min |
|---|---|---|---|
{chr(10).join(rows)}

Format 4 / format 3 (medians): {', '.join(f'{i.value} {r:.2f}' for i, r in ratio.items())}.
Labels identical: {', '.join(f'{i.value} {a}/{n}' for i, (a, n) in same.items())}.
"""
    write_text(args.out, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
