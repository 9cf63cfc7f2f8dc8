"""Can a threshold buy whole-grid geometry IoU? The default bundle with its free score raised by DELTA.

    python -m benchmarks.free_bias_sweep --towns TOWN [TOWN ...] --prior-data TRAIN_TOWN --deltas 0 1 2 3 \
        [--bundle DIR] [--out benchmarks/results/free_bias_sweep.md]

For each DELTA a copy of the bundle is made whose heads.npz `free_bias` is raised by DELTA (every voxel's free
score, main branch, before the softmax: a higher DELTA calls more voxels free; bundle.json's sha256 of heads.npz
updated), and scored on the towns by benchmarks/default_bundle_towns.py (the runtime, `ago infer` + `ago metric`,
beside the no-image predictors). Use towns that are not the ones the bundle is reported on: this sweep looks at
their scores to choose.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import default_bundle_towns

REPO = Path(__file__).resolve().parents[1]


def biased_copy(src: Path, dst: Path, delta: float) -> Path:
    """A copy of bundle `src` at `dst` whose free score is raised by `delta` (heads.npz free_bias)."""
    shutil.copytree(src, dst)
    with np.load(dst / "heads.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["free_bias"] = (arrays["free_bias"] + np.float32(delta)).astype(arrays["free_bias"].dtype)
    np.savez(dst / "heads.npz", **arrays)
    from ago_runtime.predict.contract import file_sha256

    meta = json.loads((dst / "bundle.json").read_text())
    meta["files"]["heads"].update(sha256=file_sha256(dst / "heads.npz"), size=(dst / "heads.npz").stat().st_size)
    (dst / "bundle.json").write_text(json.dumps(meta, indent=1))
    return dst


def main(argv=None) -> None:
    from ago_runtime.predict.bundle import resolve_bundle

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--towns", nargs="+", required=True)
    ap.add_argument("--prior-data", required=True)
    ap.add_argument("--deltas", nargs="+", type=float, default=[0.0, 1.0, 2.0, 3.0])
    ap.add_argument("--bundle", default=None, help="default: the shipped default bundle")
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/free_bias_sweep.md"))
    args = ap.parse_args(argv)
    src = Path(resolve_bundle(args.bundle))
    started, rows = time.time(), []
    with tempfile.TemporaryDirectory(prefix="ago-free-bias-") as tmp:
        for d in args.deltas:
            b = biased_copy(src, Path(tmp) / f"b{d}", d)
            res = default_bundle_towns.main(["--towns", *args.towns, "--prior-data", args.prior_data,
                                             "--bundle", str(b), "--out", str(Path(tmp) / f"b{d}.md")])
            scores = [s for _, s in res["rows"]]
            mean = {k: [float(np.nanmean([s[k][i] for s in scores])) for i in range(3)] for k in scores[0]}
            rows.append((d, mean))
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    cmd = "python -m benchmarks.free_bias_sweep " + " ".join(argv if argv is not None else sys.argv[1:])
    f = lambda v: " / ".join(f"{x:.2f}" for x in v)   # noqa: E731
    lines = ["# The default bundle with its free score raised by DELTA: what a threshold buys", "",
             f"Command: `{cmd}` ({time.time() - started:.0f} s; commit {commit}; "
             f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}). Bundle: `{src}`; towns: "
             + ", ".join(f"`{t}`" for t in args.towns) + f". CPU: {default_bundle_towns.cpu_line()}.", "",
             "Each cell: mean over the towns of mIoU / geometry IoU / geometry IoU above the ground (z > 0.2 m), "
             "benchmarks/default_bundle_towns.py's measures.", "",
             "| DELTA (free score + DELTA) | bundle | ground slab | scene prior |", "|---:|---:|---:|---:|"]
    for d, m in rows:
        lines.append(f"| {d:g} | **{f(m['bundle'])}** | {f(m['ground slab'])} | {f(m['scene prior'])} |")
    text = "\n".join(lines) + "\n"
    from ago_runtime.atomic import write_text

    write_text(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
