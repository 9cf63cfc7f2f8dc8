"""The planes graph of two or more bundles side by side (e.g. one model exported by two versions of `ago export`).

    python -m benchmarks.planes_graph_ab --bundle before=DIR --bundle after=DIR [--int8] [--openvino] [--rounds 5]
        [--reps 10] [--out benchmarks/results/planes_upsampling.md]

Each (bundle, runtime) pair runs in a child process of its own (several OpenVINO models and onnxruntime sessions
in one process slow each other down on a 2-core machine), the children alternating over --rounds rounds; each
child opens the planes graph, runs it once, then times --reps runs and reports their median. Inputs: the real
nuScenes keyframe of ../shared when present (else the exporter's synthetic frame), preprocessed for the first
bundle. Runtimes: onnxruntime's CPU provider with the runtime's session options; with --openvino, OpenVINO's CPU
device in fp32 (what `--device openvino` runs); --int8 adds each bundle's int8 planes graph. Outputs are compared
with the first bundle's on the same runtime and graph (max |difference|). Records the CPU and its flags.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def child(bundle: str, runtime: str, graph: str, reps: int, inputs: str, outputs: str) -> dict:
    from ago_runtime.predict.bundle import Bundle

    b = Bundle.load(bundle)
    path = b.encoder_graphs("int8" if graph == "int8" else None)[0].path
    feed_arrays = dict(np.load(inputs))
    if runtime == "onnxruntime":
        import onnxruntime as ort

        from ago_runtime.cache import session_options

        sess = ort.InferenceSession(str(path), session_options(), providers=["CPUExecutionProvider"])
    else:
        from ago_runtime.openvino_session import open_openvino_session
        from ago_runtime.providers import Precision

        sess = open_openvino_session(path, None, Precision.FP32)
    feed = dict(zip([i.name for i in sess.get_inputs()], feed_arrays.values()))
    run = lambda: sess.run(None, feed)  # noqa: E731
    out = run()
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        out = run()
        times.append(time.perf_counter() - t)
    np.savez(outputs, *[np.asarray(o) for o in out])
    return {"median_s": statistics.median(times), "graph": str(path)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", action="append", default=[], help="NAME=DIR (two or more)")
    ap.add_argument("--int8", action="store_true")
    ap.add_argument("--openvino", action="store_true")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--work", type=Path, default=REPO / "work" / "planes_graph_ab")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "planes_graph_ab.md")
    ap.add_argument("--child", nargs=6, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        bundle, runtime, graph, reps, inputs, outputs = args.child
        print(json.dumps(child(bundle, runtime, graph, int(reps), inputs, outputs)))
        return

    from ago_runtime.atomic import write_text
    from ago_runtime.predict.bundle import Bundle
    from ago_runtime.predict.predictor import prepare_inputs
    from benchmarks.default_bundle_towns import cpu_line
    from benchmarks.paper_scale import load_frame, require_openvino

    bundles = dict(b.split("=", 1) for b in args.bundle)
    if len(bundles) < 2:
        print("error: --bundle: give two or more NAME=DIR", file=sys.stderr)
        sys.exit(2)
    if args.openvino:
        require_openvino()
    args.work.mkdir(parents=True, exist_ok=True)
    images, rig, frame = load_frame()
    first = Bundle.load(next(iter(bundles.values())))
    x, m = prepare_inputs(first, images, rig)
    inputs = args.work / "inputs.npz"
    np.savez(inputs, images=x, ego2img=m)
    runtimes = ["onnxruntime"] + (["openvino"] if args.openvino else [])
    graphs = ["fp32"] + (["int8"] if args.int8 else [])
    pairs = [(r, g, n) for r in runtimes for g in graphs for n in bundles]
    times: dict = {p: [] for p in pairs}
    load0 = os.getloadavg()
    env = {**os.environ, "PYTHONPATH": str(REPO), "AGO_NO_PROGRESS": "1"}
    for r in range(args.rounds):
        for runtime, graph, name in pairs:
            outputs = args.work / f"out_{runtime}_{graph}_{name}.npz"
            proc = subprocess.run([sys.executable, "-m", "benchmarks.planes_graph_ab", "--child",
                                   bundles[name], runtime, graph, str(args.reps), str(inputs), str(outputs)],
                                  capture_output=True, text=True, env=env, cwd=str(REPO))
            if proc.returncode != 0:
                sys.exit(f"child {name} {runtime} {graph} failed:\n{proc.stderr[-2000:]}")
            times[(runtime, graph, name)].append(json.loads(proc.stdout.strip().splitlines()[-1])["median_s"])
        print(f"round {r + 1} of {args.rounds} done", flush=True)
    load1 = os.getloadavg()
    ref_name = next(iter(bundles))
    base = statistics.median(times[("onnxruntime", "fp32", ref_name)])
    cmd = "python -m benchmarks.planes_graph_ab " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    lines = ["# The planes graph of bundles side by side", "",
             f"Command: `{cmd}` (commit {commit}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; load average "
             f"{load0[0]:.1f} at the start, {load1[0]:.1f} at the end).", "",
             f"CPU: {cpu_line()}.", "",
             "Bundles: " + ", ".join(f"{n} = `{d}`" for n, d in bundles.items()) + f". Frame: {frame}. Each cell: the "
             f"median over {args.rounds} rounds of each child's median of {args.reps} runs (one child process per "
             "bundle, runtime and graph, alternating).", "",
             "| runtime | graph | bundle | planes graph (ms) | vs onnxruntime fp32 of " + ref_name + " | max abs diff to "
             + ref_name + " (same runtime and graph) |", "|---|---|---|---:|---:|---:|"]
    for runtime, graph, name in pairs:
        t = statistics.median(times[(runtime, graph, name)])
        ref = np.load(args.work / f"out_{runtime}_{graph}_{ref_name}.npz")
        got = np.load(args.work / f"out_{runtime}_{graph}_{name}.npz")
        diff = max(float(np.abs(ref[k] - got[k]).max()) for k in ref.files)
        lines.append(f"| {runtime} | {graph} | {name} | {1e3 * t:.1f} | {base / t:.2f}x | {diff:.2g} |")
    write_text(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
