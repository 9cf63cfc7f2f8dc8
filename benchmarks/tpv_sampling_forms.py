"""The TPV encoder of the `full` preset exported to ONNX in several forms of its sampling, timed side by side
in onnxruntime on one frame's geometry (issue 39).

    python -m benchmarks.tpv_sampling_forms [--rounds 3] [--out benchmarks/results/tpv_sampling_forms.md]

Forms (all the same function; the encoder alone: FPN maps -> TPV queries, as ago_export.graphs.ExportTPV):
- compact: what `ago export` writes: only the (camera, pillar point, query) entries a camera sees are sampled;
- static: `ago export --static-sampling`: every entry sampled, the unseen ones weighted by 0;
- static, einsum: static with the weighted sum as one einsum over the samples (onnxruntime Einsum), so that
  no (heads, C, samples, Q) product is written;
- static, batched MatMul: the same as a MatMul (heads, Q, C, S) x (heads, Q, S, 1);
- static, query-major: GridSample writes (heads, C, Q, samples) (its grid transposed in the graph) and the
  weighted sum runs over the last axis.
The variants swap `tpv_canvas.weighted_samples` while they are traced. Random weights (offsets and attention
weights drawn small, as after training's init), random FPN maps of the paper's sizes; the rig is the real
nuScenes keyframe's of ../shared when present, else Rig.nuscenes_like(1600, 900). Each figure is the best and
the median of the rounds; a round runs each form in a fresh child process in turn (one at a time: the static
forms hold GBs): one run to warm up, then the best of two timed runs; the op split is onnxruntime's profile of
the first round's last run (its profiling overhead included).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

import ago_train.model.tpv_canvas as tc
from ago_export.graphs import ExportTPV
from ago_runtime.geometry.camera import Rig
from ago_runtime.geometry.preprocess import Preprocess
from ago_train.model import ModelConfig

REPO = Path(__file__).resolve().parents[1]
SHARED_SAMPLE = REPO.parent / "shared" / "data" / "nuscenes-sample"
SHIPPED_WEIGHTED_SAMPLES = tc.weighted_samples


def einsum_form(canvas, grid, w):
    sampled = torch.nn.functional.grid_sample(canvas, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return torch.einsum("hcsq,hsq->hcq", sampled, w)


def matmul_form(canvas, grid, w):
    sampled = torch.nn.functional.grid_sample(canvas, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return torch.matmul(sampled.permute(0, 3, 1, 2), w.permute(0, 2, 1).unsqueeze(-1)).squeeze(-1).permute(0, 2, 1)


def query_major_form(canvas, grid, w):
    sampled = torch.nn.functional.grid_sample(canvas, grid.transpose(1, 2), mode="bilinear", padding_mode="zeros",
                                              align_corners=False)      # (h, C, Q, S)
    return (sampled * w.transpose(1, 2).unsqueeze(1)).sum(3)


FORMS = {  # name -> (static_sampling, weighted_samples while tracing)
    "compact (ago export)": (False, SHIPPED_WEIGHTED_SAMPLES),
    "static (--static-sampling)": (True, SHIPPED_WEIGHTED_SAMPLES),
    "static, einsum": (True, einsum_form),
    "static, batched MatMul": (True, matmul_form),
    "static, query-major": (True, query_major_form),
}


def frame_ego2img(cfg) -> tuple[np.ndarray, str]:
    if (SHARED_SAMPLE / "mmdet3d_info.pkl").is_file():
        from ago_runtime.formats.mmdet3d_info import load_mmdet3d_info

        f = load_mmdet3d_info(SHARED_SAMPLE / "mmdet3d_info.pkl", SHARED_SAMPLE)[0]
        rig, name = f.rig, f"the rig of nuScenes keyframe {f.token}"
    else:
        rig, name = Rig.nuscenes_like(1600, 900), "Rig.nuscenes_like(1600, 900)"
    return Preprocess(cfg.image_width, cfg.image_height).ego2img(rig).astype(np.float32), name


def session(path: Path, profile_prefix: str | None = None) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.log_severity_level = 3
    if profile_prefix:
        so.enable_profiling = True
        so.profile_file_prefix = profile_prefix
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def op_split(profile_file: str, top: int = 6) -> list[tuple[str, float]]:
    """Seconds per operator type in the profile's last run."""
    events = json.loads(Path(profile_file).read_text())
    run = [e for e in events if e.get("name") == "model_run"][-1]
    by_op: collections.Counter = collections.Counter()
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time") and run["ts"] <= e["ts"] <= run["ts"] + run["dur"]:
            by_op[e["args"]["op_name"]] += e["dur"] / 1e6
    return by_op.most_common(top)


def build_model():
    cfg = ModelConfig.preset("full")
    cfg.pretrained = False
    torch.manual_seed(0)
    model = cfg.build(load_weights=False).eval()
    with torch.no_grad():
        for name, p in model.encoder.named_parameters():
            if "sampling_offsets.weight" in name or "attention_weights.weight" in name:
                p.normal_(0, 0.02)
    return cfg, model


def child_export(index: str, tmp: str) -> dict:
    """Export form `index` to tmp/form<i>.onnx (the feeds: tmp/feeds.npz, made by the first call); its
    outputs on the feeds -> tmp/out<i>.npz."""
    cfg, model = build_model()
    tmp_dir, i = Path(tmp), int(index)
    m, rig_name = frame_ego2img(cfg)
    if not (tmp_dir / "feeds.npz").is_file():
        g = np.random.default_rng(0)
        feats = [g.standard_normal((cfg.num_cameras, cfg.tpv_dim, cfg.image_height // s, cfg.image_width // s),
                                   dtype=np.float32) for s in tc.LEVEL_STRIDES]
        np.savez(tmp_dir / "feeds.npz", f0=feats[0], f1=feats[1], f2=feats[2], ego2img=m)
    feed = dict(np.load(tmp_dir / "feeds.npz"))
    valid = {p: float((model.encoder.canvas.frames[p](torch.from_numpy(m))["weight"] > 0).float().mean())
             for p in tc.PLANES}
    static, form = list(FORMS.values())[i]

    class Encoder(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.tpv = ExportTPV(model.encoder, static_sampling=static)

        def forward(self, f0, f1, f2, ego2img):
            q = self.tpv([f0, f1, f2], ego2img)
            return q["xy"], q["xz"], q["yz"]

    path = tmp_dir / f"form{i}.onnx"
    tc.weighted_samples = form
    try:
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            torch.onnx.export(Encoder().eval(), tuple(torch.from_numpy(feed[k]) for k in feed), str(path),
                              dynamo=False, opset_version=17, input_names=list(feed), do_constant_folding=True)
    finally:
        tc.weighted_samples = SHIPPED_WEIGHTED_SAMPLES
    out = session(path).run(None, feed)
    np.savez(tmp_dir / f"out{i}.npz", *out)
    return {"valid": valid, "rig": rig_name}


def child_time(path: str, profile_prefix: str) -> dict:
    """One warm-up run, then the best of two timed runs (a session is reused frame after frame; with a profile
    prefix: the op split of the last run)."""
    feed = dict(np.load(Path(path).parent / "feeds.npz"))
    s = session(Path(path), profile_prefix or None)
    s.run(None, feed)
    runs = []
    for _ in range(2):
        t = time.perf_counter()
        s.run(None, feed)
        runs.append(time.perf_counter() - t)
    res = {"s": min(runs)}
    if profile_prefix:
        res["ops"] = op_split(s.end_profiling())
    return res


def run_child(*args: str) -> dict:
    r = subprocess.run([sys.executable, "-m", "benchmarks.tpv_sampling_forms", "--child", *args], capture_output=True,
                       text=True, env={**os.environ, "PYTHONPATH": str(REPO)}, cwd=REPO)
    if r.returncode != 0:
        raise SystemExit(f"child {args} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "tpv_sampling_forms.md")
    ap.add_argument("--work", type=Path, help="folder for the exported forms (default: a new temp folder); forms "
                                              "already there are reused")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        name, *rest = args.child
        print(json.dumps({"export": child_export, "time": child_time}[name](*rest)))
        return
    tmp = args.work or Path(tempfile.mkdtemp(prefix="tpv-forms-"))
    tmp.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(FORMS):
        if not (tmp / f"info{i}.json").is_file():
            (tmp / f"info{i}.json").write_text(json.dumps(run_child("export", str(i), str(tmp))))
        print(f"exported {name}", flush=True)
    info = json.loads((tmp / "info0.json").read_text())
    valid, rig_name = info["valid"], info["rig"]
    outputs = {n: list(np.load(tmp / f"out{i}.npz").values()) for i, n in enumerate(FORMS)}
    first = next(iter(FORMS))
    diff = {n: max(float(np.abs(a - b).max()) for a, b in zip(outputs[n], outputs[first])) for n in FORMS}
    times: dict = {n: [] for n in FORMS}
    splits = {}
    for r in range(args.rounds):
        for i, n in enumerate(FORMS):
            res = run_child("time", str(tmp / f"form{i}.onnx"), str(tmp / f"prof{i}") if r == 0 else "")
            times[n].append(res["s"])
            splits.setdefault(n, res.get("ops"))
        print(f"round {r + 1}: " + ", ".join(f"{n} {times[n][-1]:.2f} s" for n in FORMS), flush=True)
    base = min(times["static (--static-sampling)"])
    lines = ["# The TPV encoder's sampling forms in onnxruntime (issue 39)", "",
             f"Command: `python -m benchmarks.tpv_sampling_forms --rounds {args.rounds}` "
             f"({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, this 2-core CPU, shared with other work).", "",
             f"`full` preset encoder alone (3 layers, 100x100x16 TPV, 8 heads of 16 channels; FPN maps of 1600x928 "
             f"images in, random), {rig_name}: entries a camera sees: "
             + ", ".join(f"{p} {100 * v:.1f} %" for p, v in valid.items()) + ". "
             f"Best and median of {args.rounds} alternating rounds; max |difference| to the compact form's output.", "",
             "| form | best (s) | median (s) | vs static | max abs diff | largest operators (s, round 1, profiled) |",
             "|---|---:|---:|---:|---:|---|"]
    for n in FORMS:
        ops = ", ".join(f"{op} {s:.2f}" for op, s in splits[n])
        lines.append(f"| {n} | {min(times[n]):.2f} | {np.median(times[n]):.2f} | {base / min(times[n]):.2f}x | "
                     f"{diff[n]:.1e} | {ops} |")
    from ago_runtime.atomic import write_text

    write_text(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
