"""Interleaved A/B of the TPV encoder's forward + backward: this tree's `tpv_canvas.image_attention`
against the one of another commit, in ONE process on the same frames (so a slow or busy machine
slows both alike).

    python benchmarks/tpv_encoder_ab.py --old 5d5757b --data work/db24/synth --pseudo work/db24/pseudo

Prints the median and mean milliseconds of `encoder(feats) + backward` per frame for each version.
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import torch  # noqa: E402

import ago_train.model.tpv_canvas as tc  # noqa: E402
from train_step_speed import Batches, make_trainer  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", required=True, help="git commit whose tpv_canvas.image_attention is the baseline")
    ap.add_argument("--data", required=True)
    ap.add_argument("--pseudo", required=True)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--rounds", type=int, default=8)
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    src = subprocess.run(["git", "-C", str(REPO), "show", f"{args.old}:ago_train/model/tpv_canvas.py"],
                         check=True, capture_output=True, text=True).stdout
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "tpv_canvas_old.py"
        path.write_text(src)
        spec = importlib.util.spec_from_file_location("tpv_canvas_old", path)
        old = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(old)
        impl = {"old": old.image_attention, "new": tc.image_attention}
        t = make_trainer([], args.data, args.pseudo, Path(tmp) / "run")
        batches = Batches(t)
        frames = [batches.next()[0] for _ in range(args.frames)]
        model = t.model

        def once(batch, which) -> float:
            tc.image_attention = impl[which]
            prefix = [p.reshape(-1, *p.shape[2:]).float() for p in batch["prefix"]]
            feats = [f.detach().requires_grad_() for f in model.fpn(model.backbone.from_prefix(prefix))]
            t0 = time.perf_counter()
            planes = model.encoder(feats, batch["ego2img"])
            sum(p.square().mean() for p in planes.values()).backward()
            return time.perf_counter() - t0

        times = {"old": [], "new": []}
        for r in range(args.rounds):
            for which in (("old", "new") if r % 2 == 0 else ("new", "old")):
                times[which] += [once(b, which) for b in frames]
        tc.image_attention = impl["new"]
    result = {k: {"median_ms": round(statistics.median(v) * 1e3, 1), "mean_ms": round(statistics.mean(v) * 1e3, 1)}
              for k, v in times.items()}
    print(result)
    return result


if __name__ == "__main__":
    main()
