"""Cost of a CLIP ViT-B/16-sized text tower in a bundle: export time, file sizes, encoding speed, int8 agreement.

The tower has ViT-B/16's text shapes (12 layers of 512, 8 heads, MLP 2048, vocabulary 49408, context 77,
projection 512) with RANDOM weights (CLIPConfig's initialisation; no weights can be downloaded here), and the
byte-level BPE tokenizer of tests/clip_tiny.py (a small vocabulary: words it does not know whole are spelt in
byte tokens, so phrases are longer in tokens than with CLIP's real vocabulary). Sizes and speeds are those of the
real architecture; the int8 cosines are those of random weights, not a measurement of real CLIP's int8 error.

Measured: torch -> ONNX export time; text_encoder.onnx fp32 and dynamically quantised int8 sizes; phrases per
second encoding the shipped prompt files' phrases (batch 128) with torch fp32, ONNX fp32 and ONNX int8; cosine of
ONNX fp32 / int8 to transformers' get_text_features on those phrases. Writes benchmarks/results/clip_text_tower.md.

    python benchmarks/clip_text_tower.py
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
os.environ.setdefault("HF_HUB_OFFLINE", "1")


def write_vitb16_text_folder(folder: Path) -> Path:
    """A CLIP folder with ViT-B/16's text tower shapes (random weights), a tiny vision tower, the test tokenizer."""
    import torch
    from transformers import CLIPConfig, CLIPModel, CLIPTokenizer
    from transformers.utils import logging

    from clip_tiny import clip_vocab

    logging.disable_progress_bar()
    torch.manual_seed(0)
    vocab, merges = clip_vocab()
    bos, eos = vocab["<|startoftext|>"], vocab["<|endoftext|>"]
    cfg = CLIPConfig(text_config={"vocab_size": 49408, "hidden_size": 512, "intermediate_size": 2048,
                                  "num_hidden_layers": 12, "num_attention_heads": 8, "max_position_embeddings": 77,
                                  "bos_token_id": bos, "eos_token_id": eos, "pad_token_id": eos},
                     vision_config={"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 1,
                                    "num_attention_heads": 2, "image_size": 32, "patch_size": 8},
                     projection_dim=512)
    CLIPModel(cfg).eval().save_pretrained(folder)
    CLIPTokenizer(vocab=vocab, merges=merges).save_pretrained(folder)
    return folder


def speed(encode, phrases, repeat: int = 3) -> float:
    encode(phrases[:16])
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        encode(phrases)
        best = min(best, time.perf_counter() - t0)
    return len(phrases) / best


def main() -> None:
    import torch

    from ago_export.quantize import quantize_encoder
    from ago_runtime.atomic import write_text
    from ago_runtime.vocab.prompts import parse_prompt_file, shipped_label_spaces
    from ago_runtime.vocab.text_encoder import OnnxTextEncoder, l2_normalise
    from ago_train.text.clip import TorchClipTextEncoder, export_clip_onnx

    phrases = sorted({p for n in shipped_label_spaces() for p in parse_prompt_file(n).phrases})
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        folder = write_vitb16_text_folder(d / "clip")
        enc = TorchClipTextEncoder(folder)
        t0 = time.perf_counter()
        fp32 = export_clip_onnx(enc, d / "text_encoder.onnx")
        export_s = time.perf_counter() - t0
        int8 = d / "int8" / "text_encoder.onnx"
        int8.parent.mkdir()
        t0 = time.perf_counter()
        quantize_encoder(fp32, int8)
        quant_s = time.perf_counter() - t0
        onnx32 = OnnxTextEncoder(fp32)
        onnx8 = OnnxTextEncoder(int8, pooling="eos", tokenizer=onnx32.tokenizer, variant="onnx-int8",
                                encoder_id=enc.encoder_id)
        ref = l2_normalise(enc.raw(phrases))
        rows = []
        for name, e, size in (("torch fp32", enc, None), ("ONNX fp32", onnx32, fp32.stat().st_size),
                              ("ONNX int8", onnx8, int8.stat().st_size)):
            cos = (e.encode(phrases) * ref).sum(1)
            rows.append((name, size, speed(e.encode, phrases), cos.min(), cos.mean()))
        tokens = int(enc.tokenizer.encode(phrases)[1].sum(1).mean())
    cpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    model = next((ln.split(":", 1)[1].strip() for ln in cpu.splitlines() if ln.startswith("Model name")), "?")
    flags = next((ln.split(":", 1)[1].split() for ln in cpu.splitlines() if ln.startswith("Flags")), [])
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout.strip()
    load = os.getloadavg()
    lines = ["# CLIP ViT-B/16-sized text tower in a bundle (random weights)", "",
             "Command: `python benchmarks/clip_text_tower.py`; commit " + commit + f"; CPU {model} "
             f"({os.cpu_count()} cores; AVX512-VNNI {'yes' if 'avx512_vnni' in flags else 'no'}, AVX-VNNI "
             f"{'yes' if 'avx_vnni' in flags else 'no'}); torch threads {torch.get_num_threads()}; python "
             f"{platform.python_version()}. The machine was shared with other jobs (load average "
             f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f} at the end), so speeds are indicative.", "",
             "Shapes: 12 layers of 512, 8 heads, MLP 2048, vocabulary 49408, context 77, projection 512 (ViT-B/16's "
             "text tower), RANDOM weights (CLIPConfig's initialisation). Tokenizer: the tests' small BPE "
             f"vocabulary ({tokens} tokens per phrase on average, start and end included; real CLIP's vocabulary "
             "gives fewer). So sizes and speeds are the architecture's; the int8 cosines are random weights', not "
             "real CLIP's int8 error, which is not measured here.", "",
             f"Export (torch.onnx, opset 17): {export_s:.1f} s; dynamic int8 quantisation: {quant_s:.1f} s.", "",
             f"Phrases: the {len(phrases)} distinct phrases of the shipped prompt files, encoded in one batch; "
             "cosine to transformers' get_text_features (normalised).", "",
             "| variant | file MB | phrases/s | min cosine | mean cosine |", "|---|---|---|---|---|"]
    for name, size, sp, cmin, cmean in rows:
        lines.append(f"| {name} | {'-' if size is None else f'{size / 1e6:.1f}'} | {sp:.0f} | {cmin:.6f} | {cmean:.6f} |")
    lines += ["", "Tolerances `ago export` applies (ago_export/text_tower.py): fp32 min cosine >= 1 - 1e-5; the "
              "int8 tower ships instead of fp32 only when its min cosine >= 0.995 on the training bank's phrases "
              "and the probes.", ""]
    out = ROOT / "benchmarks" / "results" / "clip_text_tower.md"
    write_text(out, "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
