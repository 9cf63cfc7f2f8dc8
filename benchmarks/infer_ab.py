"""`ago infer` over a dataset, A/B in child processes: the warm-up run at session open (on / off), the
frames predicted at once (`--workers` 1 / 2), or the int8 variant on OpenVINO against fp32 on onnxruntime.

- warm-up: `Predictor(bundle)` runs each graph once on dummy inputs so that an interactive user's first
  frame runs at the steady-state speed; a batch pays that dummy frame for nothing (its first real frame
  takes onnxruntime's first-run allocations instead). `ago infer` runs without it.
- workers: with two, two frames run at once, each on sessions with half the cores' onnxruntime threads
  (one Predictor; ago_runtime/predict/cli.py::run_infer). `ago infer` takes two over a dataset.
- int8_openvino: `ago infer` as it is (onnxruntime, fp32) against `ago infer --int8 --device openvino` (the bundle's
  int8 planes graph on OpenVINO's CPU device; give a bundle exported with `--int8`): issue 52's whole-frame target.

Each round runs both variants in fresh child processes (order alternating), with the same bundle, dataset
and warm optimised-graph cache; the table gives the minimum and median seconds per frame (wall of
run_infer / frames: bundle load, sessions, decode, graphs, heads, npz written) and the per-round ratios
(neighbours in time, so a slow spell of this shared machine hits both).

    python -m benchmarks.infer_ab --vary workers --dataset work/synth12 --bundle work/db24/bundle_model
    python -m benchmarks.infer_ab --vary warm_up --dataset work/synth12 --bundle work/db24/bundle_model
    python -m benchmarks.infer_ab --vary int8_openvino --dataset work/synth12 --bundle BUNDLE_WITH_INT8
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
VARIANTS = {"warm_up": ("on", "off"), "workers": ("1", "2"), "int8_openvino": ("onnxruntime-fp32", "openvino-int8")}
TITLES = {"warm_up": "warm-up run at session open, on / off", "workers": "one frame at a time or two at once (`--workers`)",
          "int8_openvino": "onnxruntime fp32 against `--int8 --device openvino`"}
OPENVINO_INT8 = {"int8": True, "device": "openvino"}


def variant_kwargs(vary: str, value: str) -> dict:
    """run_infer's keyword arguments for one side of an A/B (in the child)."""
    if vary == "warm_up":
        return {"warm_up": value == "on"}
    if vary == "workers":
        return {"workers": int(value)}
    return OPENVINO_INT8 if value == "openvino-int8" else {}                # int8_openvino


def require_int8_openvino(bundle: str) -> None:
    """The openvino package and a bundle with an int8 variant, checked before any run: one `error:` line, exit 2."""
    from ago_runtime.errors import AgoInputError
    from ago_runtime.predict.bundle import Bundle, resolve_bundle
    from benchmarks.paper_scale import require_openvino

    require_openvino()
    try:
        variants = Bundle.load(resolve_bundle(bundle or None), verify_hashes=False).contract.variants
    except AgoInputError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    if "int8" not in variants:
        print(f"error: --bundle: {bundle or 'the shipped bundle'} has no int8 variant (export it with `ago export --int8`)",
              file=sys.stderr)
        sys.exit(2)


def child(bundle: str, dataset: str, out: str, vary: str, value: str, picture: str) -> dict:
    import contextlib
    import io
    import time

    from ago_runtime.predict.cli import run_infer

    kwargs = variant_kwargs(vary, value)
    t = time.perf_counter()
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        files = run_infer(dataset, None, None, bundle or None, out, None, False, picture=picture, **kwargs)
    wall = time.perf_counter() - t
    frames = len([f for f in files if str(f).endswith(".npz")])
    return {"wall_s": wall, "frames": frames, "per_frame_s": wall / frames}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vary", choices=sorted(VARIANTS), default="workers")
    ap.add_argument("--dataset", help="nuScenes-layout dataset (required)")
    ap.add_argument("--bundle", default="")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--picture", default="none")
    ap.add_argument("--out", type=Path, default=None, help="default benchmarks/results/infer_<vary>.md")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(*args.child)))
        return
    if not args.dataset:
        ap.error("--dataset is required")
    if args.vary == "int8_openvino":
        require_int8_openvino(args.bundle)
    out_path = args.out or REPO / "benchmarks" / "results" / f"infer_{args.vary}.md"
    a, b = VARIANTS[args.vary]
    env = dict(os.environ, AGO_NO_PROGRESS="1")
    res: dict = {a: [], b: []}
    load0 = " ".join(f"{x:.2f}" for x in os.getloadavg())
    with tempfile.TemporaryDirectory() as tmp:
        def run(value: str, r: int) -> dict:
            cmd = [sys.executable, "-m", "benchmarks.infer_ab", "--child", args.bundle, args.dataset, f"{tmp}/{value}{r}", args.vary,
                   value, args.picture]
            p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO)
            if p.returncode:
                raise SystemExit(p.stderr[-2000:])
            return json.loads(p.stdout.strip().splitlines()[-1])

        run(a, -1)   # fills the optimised-graph cache
        for r in range(args.rounds):
            for v in ((a, b) if r % 2 == 0 else (b, a)):
                res[v].append(run(v, r))
            print(f"round {r + 1}: {a} {res[a][-1]['per_frame_s']:.3f}, {b} {res[b][-1]['per_frame_s']:.3f} s/frame",
                  flush=True)
    load1 = " ".join(f"{x:.2f}" for x in os.getloadavg())
    frames = res[a][0]["frames"]
    from benchmarks.infer_speed import git_commit
    from benchmarks.machine import cpu_model_and_flags, speed_flags

    cpu, flags = cpu_model_and_flags()
    keep = speed_flags(flags)
    L = [f"# `ago infer`: {TITLES[args.vary]}\n",
         f"Command: `python -m benchmarks.infer_ab --vary {args.vary} --dataset {args.dataset} --rounds {args.rounds} "
         f"--picture {args.picture}" + (f" --bundle {args.bundle}" if args.bundle else "") + "`  ",
         f"Commit: {git_commit(REPO)}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.  ",
         f"CPU: {cpu}, {os.cpu_count()} cores; flags of interest: {' '.join(keep) or 'none'}.  ",
         f"Bundle: {args.bundle or 'the shipped default bundle'}; {frames} frames; load average at start {load0}, "
         f"at end {load1}.\n",
         f"| {args.vary} | s per frame, min | median | whole run, min s |", "|---|---|---|---|"]
    for v in (a, b):
        per = [x["per_frame_s"] for x in res[v]]
        L.append(f"| {v} | {min(per):.3f} | {statistics.median(per):.3f} | {min(x['wall_s'] for x in res[v]):.2f} |")
    ratios = [y["per_frame_s"] / x["per_frame_s"] for x, y in zip(res[a], res[b])]
    L.append(f"\n{b} / {a}, per round: {', '.join(f'{x:.2f}' for x in ratios)}; mean **{statistics.mean(ratios):.2f}**.\n")
    from ago_runtime.atomic import write_text

    write_text(out_path, "\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
