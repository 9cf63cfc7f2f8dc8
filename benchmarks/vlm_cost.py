"""Cost of the paper's first stage on this CPU: seconds and peak memory per camera image at the real sizes.

    python benchmarks/vlm_cost.py [--out benchmarks/results/vlm_cost.md] [--boxes 32] [--parts ...]

Random weights at the published architectures' sizes (GroundingDINO-T: Swin-T + BERT-base; -B: Swin-B; SAM ViT-B,
ViT-H; CLIP ViT-B/16): cost does not depend on the weights' values. Each part runs in its own process (peak RSS
is the process's, model included) on one nuScenes-size image (1600 x 900, a real CAM_FRONT image when
../shared/data/nuscenes-scene is there), through ago_train/vlm's own code paths:
- detector, single pass: every phrase of prompts/cw.txt in one GroundingDINO pass (PhraseDetector.detect);
- detector, per class: one pass with one class's phrases (the shortest prompt), times the number of classes
  (the per-class way of running Grounded SAM, one pass per class; extrapolated from that one measured pass);
- SAM: image embedding + one mask per box for --boxes fixed boxes (what --max-boxes caps), painted at image size;
- MaskCLIP: the dense read-out at the default input width 768 (432 x 768 -> 27 x 48).
Then the projection for nuScenes' 28,130 keyframes x 6 cameras.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

NUSCENES_IMAGES = 28_130 * 6
PARTS = ["clip-b16", "gdino-t", "gdino-b", "sam-b", "sam-h"]


def swin(embed_dim, depths, heads, window, image_size):
    return {"model_type": "swin", "embed_dim": embed_dim, "depths": depths, "num_heads": heads,
            "window_size": window, "image_size": image_size, "out_indices": [2, 3, 4]}


def test_image() -> np.ndarray:
    scene = REPO.parent / "shared" / "data" / "nuscenes-scene" / "samples" / "CAM_FRONT"
    files = sorted(scene.glob("*.jpg")) if scene.is_dir() else []
    if files:
        from ago_runtime.formats.calibration import read_image

        return read_image(files[0])
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, (900, 1600, 3), dtype=np.uint8)


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_part(name: str, boxes: int) -> dict:
    import torch

    from ago_train.vlm.loading import quiet_transformers

    from ago_train.vlm.loading import resolve_device

    quiet_transformers()
    torch.manual_seed(0)
    img = test_image()
    dev = resolve_device("cpu")   # as the verbs do: subnormal floats flushed to zero
    out = {"part": name, "threads": torch.get_num_threads()}
    t0 = time.perf_counter()
    if name.startswith("gdino"):
        from transformers import BertTokenizerFast, GroundingDinoConfig, GroundingDinoForObjectDetection

        from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file
        from ago_train.vlm.grounded_sam import GroundedSamConfig, PhraseDetector
        from vlm_tiny import bert_vocab

        backbone = swin(96, [2, 2, 6, 2], [3, 6, 12, 24], 7, 224) if name == "gdino-t" else \
            swin(128, [2, 2, 18, 2], [4, 8, 16, 32], 12, 384)
        model = GroundingDinoForObjectDetection(GroundingDinoConfig(backbone_config=backbone)).eval()
        out["params_M"] = round(sum(p.numel() for p in model.parameters()) / 1e6, 1)
        tok = BertTokenizerFast(vocab={w: i for i, w in enumerate(bert_vocab())})
        space = parse_prompt_file(resolve_prompt_file("cw"))
        out["load_s"] = round(time.perf_counter() - t0, 1)
        cfg = GroundedSamConfig()
        single = PhraseDetector(".", space.phrases, dev, model=model, tokenizer=tok)
        t = time.perf_counter()
        single.detect(img, cfg)
        out["single_pass_s"] = round(time.perf_counter() - t, 2)
        out["single_pass_tokens"] = int(single.passes[0]["input_ids"].shape[1])
        out["classes"] = space.num_classes
        one = min(space.classes, key=lambda c: len(" . ".join(c.phrases)))
        per = PhraseDetector(".", list(one.phrases), dev, model=model, tokenizer=tok)
        t = time.perf_counter()
        per.detect(img, cfg)
        out["one_class_pass_s"] = round(time.perf_counter() - t, 2)
        out["per_class_s"] = round(out["one_class_pass_s"] * space.num_classes, 1)
    elif name.startswith("sam"):
        from transformers import SamConfig, SamModel

        from ago_train.vlm.grounded_sam import BoxSegmenterSam

        vision = {} if name == "sam-b" else {"hidden_size": 1280, "num_hidden_layers": 32, "num_attention_heads": 16,
                                             "global_attn_indexes": [7, 15, 23, 31]}
        model = SamModel(SamConfig(vision_config=vision)).eval()
        out["params_M"] = round(sum(p.numel() for p in model.parameters()) / 1e6, 1)
        out["load_s"] = round(time.perf_counter() - t0, 1)
        sam = BoxSegmenterSam(".", dev, model=model)
        rng = np.random.default_rng(0)
        xy = rng.uniform([0, 0], [1400, 700], (boxes, 2))
        wh = rng.uniform(40, 200, (boxes, 2))
        b = np.concatenate([xy, xy + wh], axis=1).astype(np.float32)
        label = np.zeros(img.shape[:2], np.uint8)
        t = time.perf_counter()
        for j, mask in sam.masks(img, b):
            label[mask] = j + 1
        out["boxes"] = boxes
        out["image_s"] = round(time.perf_counter() - t, 2)
    else:
        from transformers import CLIPConfig, CLIPModel

        from ago_train.vlm.maskclip import MaskClip

        model = CLIPModel(CLIPConfig(vision_config={"patch_size": 16, "image_size": 224}, projection_dim=512)).eval()
        out["params_M"] = round(sum(p.numel() for p in model.vision_model.parameters()) / 1e6, 1)
        out["load_s"] = round(time.perf_counter() - t0, 1)
        mc = MaskClip(".", dev, model=model)
        t = time.perf_counter()
        f = mc.features(img)
        out["image_s"] = round(time.perf_counter() - t, 2)
        out["map"] = list(f.shape)
    out["peak_rss_MB"] = round(rss_mb())
    return out


def sh(cmd: str) -> str:
    try:
        return subprocess.run(cmd, shell=True, capture_output=True, text=True, timeout=30).stdout.strip()
    except Exception as e:   # noqa: BLE001 (a report line, not a check)
        return f"({e})"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "vlm_cost.md"))
    ap.add_argument("--boxes", type=int, default=32)
    ap.add_argument("--parts", nargs="*", default=PARTS)
    ap.add_argument("--part", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.part:
        print(json.dumps(run_part(a.part, a.boxes)), flush=True)
        return
    load_before = os.getloadavg()
    rows = []
    for part in a.parts:
        r = subprocess.run([sys.executable, __file__, "--part", part, "--boxes", str(a.boxes)], capture_output=True,
                           text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
        line = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
        rows.append(json.loads(line[-1]) if line else {"part": part, "error": r.stderr.strip()[-300:]})
        print(rows[-1], flush=True)
    load_after = os.getloadavg()
    by = {r["part"]: r for r in rows}
    commit = sh(f"git -C {REPO} rev-parse --short HEAD")
    lscpu = sh("lscpu | grep -E 'Model name|^CPU\\(s\\)|Thread'") + "\nSIMD flags: " + \
        sh("lscpu | grep Flags | grep -oE '(avx|amx|fma|sse4)[a-z0-9_]*' | sort -u | tr '\\n' ' '")
    lines = ["# Cost of Grounded SAM + MaskCLIP per camera image on this CPU (random weights, real sizes)", "",
             f"Command: `python benchmarks/vlm_cost.py {' '.join(shlex.quote(x) for x in sys.argv[1:])}` "
             f"(commit {commit}). Each row: one image (1600 x 900), one run, its own process; peak RSS = the process's "
             "maximum resident memory, model weights included. **The machine was shared** (2 cores, six helpers "
             f"at once): load average {load_before[0]:.2f} / {load_before[1]:.2f} / {load_before[2]:.2f} before, "
             f"{load_after[0]:.2f} / {load_after[1]:.2f} / {load_after[2]:.2f} after; times are upper bounds of "
             "what this CPU does alone. No GPU was measured.", "",
             "```", lscpu, f"python {platform.python_version()}, torch threads {rows[0].get('threads')}", "```", "",
             "| part | params (M) | seconds / image | peak RSS (MB) | notes |", "|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['part']} | - | failed | - | {r['error'][:120]} |")
        elif r["part"].startswith("gdino"):
            lines.append(f"| {r['part']} single pass ({r['classes']} classes, {r['single_pass_tokens']} tokens) | "
                         f"{r['params_M']} | {r['single_pass_s']} | {r['peak_rss_MB']} | one pass, every phrase |")
            lines.append(f"| {r['part']} per class | {r['params_M']} | {r['per_class_s']} | {r['peak_rss_MB']} | "
                         f"{r['classes']} x one measured one-class pass ({r['one_class_pass_s']} s) |")
        elif r["part"].startswith("sam"):
            lines.append(f"| {r['part']} | {r['params_M']} | {r['image_s']} | {r['peak_rss_MB']} | image embedding + "
                         f"{r['boxes']} box masks at image size |")
        else:
            lines.append(f"| {r['part']} MaskCLIP | {r['params_M']} | {r['image_s']} | {r['peak_rss_MB']} | "
                         f"map {r['map']} (C, h, w) |")
    lines += ["", f"## Projection: nuScenes, 28,130 keyframes x 6 cameras = {NUSCENES_IMAGES:,} images", "",
              "| configuration | s / image (sum of rows) | CPU-days on this machine |", "|---|---|---|"]
    for det in ("gdino-t", "gdino-b"):
        for s in ("sam-b", "sam-h"):
            if det in by and s in by and "error" not in by[det] and "error" not in by[s]:
                for mode, key in (("single pass", "single_pass_s"), ("per class", "per_class_s")):
                    total = by[det][key] + by[s]["image_s"] + by.get("clip-b16", {}).get("image_s", 0)
                    lines.append(f"| {det} ({mode}) + {s} + MaskCLIP B/16 | {total:.1f} | "
                                 f"{total * NUSCENES_IMAGES / 86400:.0f} |")
    lines += ["", "Notes: the detector rows tokenise with a small test vocabulary (tests/vlm_tiny.py) that spells words "
              "it lacks letter by letter, so the single-pass caption is longer than bert-base-uncased's would be (an "
              "upper bound on the text side). The verbs flush subnormal floats to zero on the CPU "
              "(`torch.set_flush_denormal`, ago_train/vlm/loading.py): without it SAM's image embedding was more "
              "than 10x slower here (measured once: results file of the run that found it).", "",
              "What per-class passes cost in recall against one pass with every phrase is not measured here "
              "(random weights detect nothing meaningful); only their time is. Quality with real weights is not "
              "measured here either."]
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
