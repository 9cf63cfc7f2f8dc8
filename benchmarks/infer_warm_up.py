"""`ago infer` over a dataset with and without the warm-up run at session open (A/B, child processes).

`Predictor(bundle)` runs each graph once on dummy inputs so that an interactive user's first frame runs at
the steady-state speed. A batch (`ago infer` over many frames) pays that dummy frame for nothing: its first
real frame can take onnxruntime's first-run allocations instead. Each round runs both variants in fresh
child processes (order alternating), with the same bundle, dataset and warm optimised-graph cache; the
table gives the minimum and median seconds per frame (wall of run_infer / frames: bundle load, sessions,
decode, graphs, heads, npz written; --picture none).

    python benchmarks/infer_warm_up.py --dataset work/synth12   # ago synth --scenes 2 --frames 6 --seed 5 ...
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "infer_warm_up.md"


def child(bundle: str, dataset: str, out: str, warm_up: str, picture: str) -> dict:
    import contextlib
    import io

    from ago_runtime.predict.cli import run_infer

    t = time.perf_counter()
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        files = run_infer(dataset, None, None, bundle or None, out, None, False, picture=picture,
                          warm_up=warm_up == "1")
    wall = time.perf_counter() - t
    frames = len([f for f in files if str(f).endswith(".npz")])
    return {"wall_s": wall, "frames": frames, "per_frame_s": wall / frames}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", help="nuScenes-layout dataset (required)")
    ap.add_argument("--bundle", default="")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--picture", default="none")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(*args.child)))
        return
    if not args.dataset:
        ap.error("--dataset is required")
    env = dict(os.environ, AGO_NO_PROGRESS="1")
    res = {"on": [], "off": []}
    load0 = " ".join(f"{x:.2f}" for x in os.getloadavg())
    with tempfile.TemporaryDirectory() as tmp:
        def run(variant: str, r: int) -> dict:
            cmd = [sys.executable, __file__, "--child", args.bundle, args.dataset, f"{tmp}/{variant}{r}",
                   "1" if variant == "on" else "0", args.picture]
            p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO)
            if p.returncode:
                raise SystemExit(p.stderr[-2000:])
            return json.loads(p.stdout.strip().splitlines()[-1])

        run("on", -1)   # fills the optimised-graph cache
        for r in range(args.rounds):
            order = ("on", "off") if r % 2 == 0 else ("off", "on")
            for v in order:
                res[v].append(run(v, r))
            print(f"round {r + 1}: on {res['on'][-1]['per_frame_s']:.3f} off {res['off'][-1]['per_frame_s']:.3f} s/frame",
                  flush=True)
    load1 = " ".join(f"{x:.2f}" for x in os.getloadavg())
    frames = res["on"][0]["frames"]
    L = ["# `ago infer`: warm-up run at session open, on / off\n",
         f"Command: `python benchmarks/infer_warm_up.py --dataset {args.dataset} --rounds {args.rounds} "
         f"--picture {args.picture}" + (f" --bundle {args.bundle}" if args.bundle else "") + "`  ",
         f"Bundle: {args.bundle or 'the shipped default bundle'}; {frames} frames; load average at start {load0}, "
         f"at end {load1}.\n",
         "| warm-up | s per frame, min | median | whole run, min s |", "|---|---|---|---|"]
    for v in ("on", "off"):
        per = [x["per_frame_s"] for x in res[v]]
        L.append(f"| {v} | {min(per):.3f} | {statistics.median(per):.3f} | {min(x['wall_s'] for x in res[v]):.2f} |")
    on = min(x["wall_s"] for x in res["on"])
    off = min(x["wall_s"] for x in res["off"])
    L.append(f"\nOff saves {on - off:.2f} s a run ({(on - off) / frames * 1e3:.0f} ms a frame over {frames} frames).\n")
    from ago_runtime.atomic import write_text

    write_text(args.out, "\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
