"""onnxruntime's memory pattern on or off in the runtime's sessions (issue 39): first frame, steady frame, peak RSS.

    python -m benchmarks.mem_pattern [--paper-bundle DIR] [--rounds 2] [--reps 5]
        # writes benchmarks/results/mem_pattern.md (+ .json)

The runtime turns the memory pattern off (ago_runtime.cache.session_options). With it on, onnxruntime plans
its arena from the runs it has seen per input shape; the compact planes graph's sample tensors change size
with what the cameras see, so the warm-up's plan does not fit the first real frame. Per bundle (the shipped
default bundle; with --paper-bundle a `full`-preset bundle, e.g. paper_scale.py's export of a random
checkpoint) each variant runs in fresh child processes that alternate (best of --rounds): bundle open
(with the warm-up), first frame, steady frame (median of --reps), peak RSS (VmHWM) and the labels, compared
voxel by voxel with the other variant's. Frame: the real nuScenes keyframe of ../shared when present.
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
RESULTS = REPO / "benchmarks" / "results" / "mem_pattern.md"


def child(bundle: str, pattern: str, reps: int, labels_out: str) -> dict:
    import ago_runtime.cache as cache
    import ago_runtime.predict.bank_product as bank_product
    from benchmarks.paper_scale import predictor_frames

    runtime_options = cache.session_options

    def options(*args, **kwargs):
        so = runtime_options(*args, **kwargs)
        so.enable_mem_pattern = pattern == "on"
        return so

    cache.session_options = bank_product.session_options = options
    from ago_runtime.predict.predictor import Predictor

    *_, record = predictor_frames(lambda: Predictor(bundle), reps, labels_out)
    return record


def run_child(*args: str) -> dict:
    r = subprocess.run([sys.executable, "-m", "benchmarks.mem_pattern", "--child", *args], capture_output=True,
                       text=True, env={**os.environ, "AGO_NO_PROGRESS": "1"}, cwd=REPO)
    if r.returncode != 0:
        raise SystemExit(f"child failed: {r.stderr.strip()[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--paper-bundle", default=None, help="a `full`-preset bundle (e.g. paper_scale.py's export)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--work", type=Path, default=REPO / "work" / "mem_pattern")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        bundle, pattern, reps, labels = args.child
        print(json.dumps(child(bundle, pattern, int(reps), labels)))
        return

    import numpy as np

    from ago_runtime.atomic import write_text
    from ago_runtime.predict.bundle import resolve_bundle

    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    bundles = {"shipped default (cpu preset, static sampling graph, 200x200x16 read-out)": str(resolve_bundle(None))}
    if args.paper_bundle:
        bundles["paper scale (full preset, random weights, compact sampling graph)"] = args.paper_bundle
    load_start = os.getloadavg()[0]
    results = {}
    for b, (label, bundle) in enumerate(bundles.items()):
        best = {}
        for _ in range(max(1, args.rounds)):
            for pattern in ("on", "off"):
                res = run_child(bundle, pattern, str(args.reps), str(work / f"labels_{b}_{pattern}.npy"))
                print(label, pattern, res, flush=True)
                old = best.get(pattern)
                best[pattern] = res if old is None else {k: (min(v, res[k]) if isinstance(v, float) else v)
                                                         for k, v in old.items()}
        agree = float((np.load(work / f"labels_{b}_on.npy") == np.load(work / f"labels_{b}_off.npy")).mean())
        results[label] = {"on": best["on"], "off": best["off"], "agreement": agree}
    command = "python -m benchmarks.mem_pattern " + " ".join(sys.argv[1:])
    lines = ["# onnxruntime's memory pattern in the runtime's sessions (issue 39)", "",
             f"Command: `{command.strip()}` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, this 2-core "
             f"CPU; load average {load_start:.2f} at the start, {os.getloadavg()[0]:.2f} at the end). Each figure the "
             f"best of {args.rounds} alternating rounds of fresh processes; frame: "
             f"{next(iter(results.values()))['on']['frame']}.", "",
             "| bundle | memory pattern | open + warm-up (s) | first frame (s) | steady frame (s) | first / steady | "
             "peak RSS (MiB) |", "|---|---|---:|---:|---:|---:|---:|"]
    for label, r in results.items():
        for pattern in ("on", "off"):
            x = r[pattern]
            name = pattern + (" (the runtime's)" if pattern == "off" else "")
            lines.append(f"| {label} | {name} | {x['open_s']:.2f} | {x['first_s']:.3f} | {x['steady_s']:.3f} | "
                         f"{x['first_s'] / x['steady_s']:.2f} | {x['rss_mib']:.0f} |")
    lines.append("")
    lines += [f"Labels, pattern on vs off: {100 * r['agreement']:.3f} % of the voxels agree ({label})."
              for label, r in results.items()]
    write_text(args.out, "\n".join(lines) + "\n")
    write_text(args.out.with_suffix(".json"), json.dumps({"command": command, "results": results}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
