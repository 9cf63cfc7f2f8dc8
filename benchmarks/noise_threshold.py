"""How close are WordNet nouns to the label phrases? Picks the noise near-synonym threshold.

For the noise candidates (filters 1-4 of ago_train/text/noise.py) prints how many words have a
max cosine to any shipped label phrase above each threshold, and 12 random words (with their
nearest label phrase) per cosine band. Writes benchmarks/results/noise_threshold.md.

    python -m benchmarks.noise_threshold
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from ago_runtime.atomic import write_text  # noqa: E402
from ago_train.text.minilm import TorchMiniLMEncoder  # noqa: E402
from ago_train.text.noise import NEAR_SYNONYM_COS, candidate_words, label_phrases  # noqa: E402


def main() -> None:
    enc = TorchMiniLMEncoder(batch_size=256)
    labels = label_phrases()
    words = candidate_words(enc.tokenizer, labels)
    sim = enc.encode(words) @ enc.encode(labels).T
    best, arg = sim.max(1), sim.argmax(1)
    rng = np.random.default_rng(0)
    lines = ["# Noise words: cosine to the nearest label phrase", "",
             "Command: `python -m benchmarks.noise_threshold` (torch fp32 MiniLM; "
             f"{len(words)} candidates, {len(labels)} label phrases/class names of all shipped prompt files).", "",
             "| threshold | words above |", "|---|---|"]
    for t in (0.4, 0.45, 0.5, 0.55, 0.6, 0.65, 0.7, 0.8):
        lines.append(f"| {t} | {(best > t).sum()} |")
    lines += ["", "| band | words | random examples (word ~ nearest label phrase) |", "|---|---|---|"]
    for lo, hi in ((0.4, 0.45), (0.45, 0.5), (0.5, 0.55), (0.55, 0.6), (0.6, 0.7), (0.7, 1.0)):
        idx = np.where((best > lo) & (best <= hi))[0]
        pick = rng.choice(idx, size=min(12, len(idx)), replace=False)
        ex = ", ".join(f"{words[i]}~{labels[arg[i]]}" for i in pick)
        lines.append(f"| {lo}-{hi} | {len(idx)} | {ex} |")
    lines += ["", f"Threshold in use: NEAR_SYNONYM_COS = {NEAR_SYNONYM_COS}.", ""]
    write_text(ROOT / "benchmarks/results/noise_threshold.md", "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
