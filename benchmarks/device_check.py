"""The runtime on accelerators (issue 39): each bundle on each device and precision, against CPU fp32.

    python -m benchmarks.device_check [--devices cpu:fp32,cuda:fp32,tensorrt:fp32,tensorrt:fp16] \
        [--paper-scale] [--reps 5] [--out benchmarks/results/device_check.md]

The script to run, once, on a machine with a GPU (onnxruntime-gpu installed: `bash scripts/setup.sh --device
cuda`; TensorRT when its libraries are there). Bundles: the shipped default bundle and, with --paper-scale,
the `full` preset exported from a random checkpoint (cost only; made here with the training extra, or given
with --paper-bundle DIR). Frame: the real nuScenes keyframe of ../shared (else the exporter's synthetic
frame). Per bundle and device: bundle open (TensorRT: engine build included the first time), first frame,
steady frame (median of --reps from the preprocessed tensors), and the labels' agreement with CPU fp32
voxel by voxel. With --paper-scale the full preset comes in both of the planes graph's sampling forms: the
compact one `ago export` writes (data-dependent sample counts: NonZero, ScatterElements) and the static one of
`ago export --static-sampling` (every camera and pillar point sampled: fixed shapes, what TensorRT engines and
CUDA graphs prefer); each is compared with its own CPU fp32, and the static form's CPU fp32 with the compact
one's. A device this onnxruntime lacks is written as refused, with the refusal, not skipped
silently. Every device runs in its own child process (peak RSS per child). On a machine without a package
registry, carry the wheel: `pip download --no-deps 'onnxruntime-gpu>=1.17,<1.33' -d wheels/` here, then
`pip uninstall -y onnxruntime && pip install wheels/onnxruntime_gpu-*.whl` there.

OpenVINO on this CPU: `--device openvino` is the OpenVINO runtime (the `openvino` extra, beside onnxruntime), so
its children run in this environment (`--devices cpu:fp32,openvino:fp32,openvino:bf16`); bf16 against fp32 over a
town of frames: benchmarks/bf16_openvino.py. `--python DEVICE=ENV/bin/python` runs a device's children in another
environment (with this repository on PYTHONPATH), e.g. onnxruntime-gpu kept apart from the CPU build.
benchmarks/results/openvino_cpu.md was measured through the earlier onnxruntime-openvino route (its own venv).
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
RESULTS = REPO / "benchmarks" / "results" / "device_check.md"


def child(bundle: str, device: str, precision: str, reps: int, labels_out: str) -> dict:
    from ago_runtime.errors import AgoInputError
    from ago_runtime.predict.predictor import Predictor
    from benchmarks.paper_scale import predictor_frames

    try:
        p, *_, record = predictor_frames(lambda: Predictor(bundle, device=device, precision=precision), reps,
                                         labels_out)
    except AgoInputError as e:
        return {"refused": str(e)}
    return {**record, "providers": p.encoder.planes.get_providers(),
            "onnxruntime": __import__("onnxruntime").__version__}


def paper_bundle(work: Path, static_sampling: bool) -> str:
    """The full preset exported from a random checkpoint into `work` (made once, reused), in the compact or the
    static sampling form."""
    from ago_export.export import export_bundle
    from ago_export.testing import random_checkpoint

    out = work / ("paper_bundle_static" if static_sampling else "paper_bundle")
    if not (out / "bundle.json").is_file():
        ckpt = work / "full_random.pt"
        if not ckpt.is_file():
            random_checkpoint(ckpt, "full", prompts="cw", seed=0)
        export_bundle(ckpt, out, bank_prompts=[], parity=False, log=print, static_sampling=static_sampling)
    return str(out)


def run_child(*args: str, python: str | None = None) -> dict:
    """One device's child: in this interpreter, or in `python` (another environment) with this repository on
    PYTHONPATH."""
    env = {**os.environ, "AGO_NO_PROGRESS": "1"}
    if python:
        env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    r = subprocess.run([python or sys.executable, "-m", "benchmarks.device_check", "--child", *args],
                       capture_output=True, text=True, env=env, cwd=REPO)
    if r.returncode != 0:
        return {"failed": r.stderr.strip().splitlines()[-1][:300] if r.stderr.strip() else f"exit {r.returncode}"}
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--devices", default="cpu:fp32,cuda:fp32,tensorrt:fp32,tensorrt:fp16")
    ap.add_argument("--paper-scale", action="store_true", help="also the full preset (random weights)")
    ap.add_argument("--paper-bundle", default=None, help="an exported full-preset bundle to use")
    ap.add_argument("--paper-static-bundle", default=None,
                    help="the same exported with --static-sampling (else made here with --paper-scale)")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--work", type=Path, default=REPO / "work" / "device_check")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--python", action="append", default=[], metavar="DEVICE=PYTHON",
                    help="run DEVICE's children with another interpreter (an environment with that onnxruntime build)")
    ap.add_argument("--rounds", type=int, default=1, help="alternate the devices this many times; best of the rounds")
    ap.add_argument("--child", nargs=5, help=argparse.SUPPRESS)
    args = ap.parse_args()
    pythons = {}
    for item in args.python:
        device, sep, python = item.partition("=")
        if not sep or not Path(python).is_file():
            print(f"error: --python: expected DEVICE=PATH to an interpreter, got {item!r}", file=sys.stderr)
            sys.exit(2)
        pythons[device] = python
    if args.child:
        bundle, device, precision, reps, labels = args.child
        print(json.dumps(child(bundle, device, precision, int(reps), labels)))
        return

    import numpy as np

    from ago_runtime.predict.bundle import resolve_bundle

    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    bundles = {"shipped default (cpu preset, 200x200x16 read-out)": str(resolve_bundle(None))}
    if args.paper_scale or args.paper_bundle:
        paper = args.paper_bundle or paper_bundle(work, static_sampling=False)
        static = args.paper_static_bundle or paper_bundle(work, static_sampling=True)
        bundles["paper scale (full preset, random weights)"] = paper
        bundles["paper scale, --static-sampling"] = static
    devices = [tuple(d.split(":")) for d in args.devices.split(",")]
    rows = []
    cpu_labels = {}   # bundle label -> its CPU fp32 labels (the static form is also compared with the compact one)
    for b, (label, bundle) in enumerate(bundles.items()):
        ref = None
        best = {}
        for _ in range(max(1, args.rounds)):          # devices alternate; each figure the best of the rounds
            for device, precision in devices:
                labels = work / f"labels_{b}_{device}_{precision}.npy"
                res = run_child(bundle, device, precision, str(args.reps), str(labels), python=pythons.get(device))
                if "steady_s" in res:
                    got = np.load(labels)
                    if (device, precision) == ("cpu", "fp32"):
                        ref = got
                        cpu_labels[label] = got
                    res["agreement"] = float((got == ref).mean()) if ref is not None else None
                    res["python"] = pythons.get(device, sys.executable)
                old = best.get((device, precision))
                if old is None or ("steady_s" in res and ("steady_s" not in old or
                                                          res["steady_s"] < old["steady_s"])):
                    best[(device, precision)] = res
                print(label, device, precision, {k: v for k, v in res.items() if k != "providers"}, flush=True)
        rows += [(label, device, precision, best[(device, precision)]) for device, precision in devices]
    import onnxruntime as ort

    lines = ["# The runtime on accelerators (issue 39)", "",
             f"Command: `python -m benchmarks.device_check {' '.join(sys.argv[1:])}` "
             f"({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; onnxruntime {ort.__version__}, providers "
             f"{', '.join(ort.get_available_providers())}).", "",
             "| bundle | device | precision | onnxruntime | open (s) | first frame (s) | steady frame (s) | "
             "peak RSS (MiB) | labels = CPU fp32 (%) |", "|---|---|---|---|---:|---:|---:|---:|---:|"]
    forms = [cpu_labels.get(k) for k in ("paper scale (full preset, random weights)", "paper scale, --static-sampling")]
    if all(f is not None for f in forms) and forms[0].shape == forms[1].shape:
        same = 100 * float((forms[0] == forms[1]).mean())
        lines[4:4] = [f"CPU fp32 labels, static sampling = compact sampling: {same:.3f} % of the voxels.", ""]
    for label, device, precision, r in rows:
        if "steady_s" in r:
            agree = f"{100 * r['agreement']:.3f}" if r.get("agreement") is not None else "(no CPU fp32 run)"
            lines.append(f"| {label} | {device} | {precision} | {r.get('onnxruntime', '')} | {r['open_s']:.2f} | "
                         f"{r['first_s']:.3f} | {r['steady_s']:.3f} | {r['rss_mib']:.0f} | {agree} |")
        else:
            lines.append(f"| {label} | {device} | {precision} | | {r.get('refused') or r.get('failed')} | | | | |")
    from ago_runtime.atomic import write_text

    write_text(args.out, "\n".join(lines) + "\n")
    write_text(args.out.with_suffix(".json"), json.dumps(rows, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
