"""`ago prompts export-encoder` and `ago prompts noise` (need torch), and the `--encoder torch` choice.

export-encoder [-o P]  write MiniLM as ONNX (needs torch) - default the ago cache
noise [-o P]           build the WordNet noise-word bank for training (needs torch + nltk data);
                       --text-encoder DIR: with a CLIP folder's text tower

`register(app)` adds both verbs to ago_runtime's `ago prompts` group (ago_runtime/vocab/cli.py). The
`--encoder torch` choice is not registered here: ago_runtime.vocab.text_encoder names the torch MiniLM's
module as data (`EXTRA_ENCODERS`). Imports nothing heavy at import time.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ago_runtime.errors import require_torch


def export_encoder(output: Optional[Path] = typer.Option(None, "-o", "--output",
                                                         help="ONNX file (default ~/.cache/ago/text_encoder/all-MiniLM-L6-v2.onnx)")):
    """Export all-MiniLM-L6-v2 (bundled weights) to ONNX fp32, for runtime use without torch."""
    require_torch("prompts export-encoder")
    import numpy as np

    from ago_runtime.outputs import check_output_file
    from ago_runtime.vocab.text_encoder import cached_encoder_path

    check_output_file(output if output is not None else cached_encoder_path(), "-o")

    from .minilm import TorchMiniLMEncoder, export_onnx

    from ago_runtime.vocab.text_encoder import OnnxTextEncoder

    path = export_onnx(output)
    test = ["car", "a traffic cone on the road", "vegetation"]
    cos = (OnnxTextEncoder(path).encode(test) * TorchMiniLMEncoder().encode(test)).sum(1).min()
    typer.echo(f"{path}: ONNX opset 17, inputs input_ids/attention_mask (int64, dynamic batch x sequence), "
               f"output normalised embeddings (batch, 384); min cosine to torch {float(np.round(cos, 6))}")


def noise(output: Optional[Path] = typer.Option(None, "-o", "--output", help="noise bank file (default: the ago cache)"),
          force: bool = typer.Option(False, "--force", help="rebuild even if the file exists"),
          text_encoder: Optional[Path] = typer.Option(None, "--text-encoder", help="a CLIP save_pretrained folder: "
                                                      "encode the words with its text tower (default: MiniLM)")):
    """Build the noise-word bank (WordNet nouns minus label phrases and near-synonyms)."""
    from ago_runtime.vocab.model_folder import clip_text_encoder

    if output is not None:
        from ago_runtime.outputs import check_output_file

        check_output_file(output, "-o")
    encoder = clip_text_encoder(text_encoder, verb="prompts noise") if text_encoder is not None else None
    require_torch("prompts noise")
    from .noise import NoiseBank, ensure_noise_bank

    path = ensure_noise_bank(output, force=force, encoder=encoder)
    nb = NoiseBank.load(path)
    typer.echo(f"{path}: {len(nb.words)} noise words, {nb.meta.get('encoder_id')}, dim {nb.dim}, "
               f"{path.stat().st_size / 1e6:.1f} MB")


def register(app: typer.Typer) -> None:
    from ago_runtime.vocab.cli import prompts_group

    group = prompts_group(app)
    group.command("export-encoder")(export_encoder)
    group.command("noise")(noise)
