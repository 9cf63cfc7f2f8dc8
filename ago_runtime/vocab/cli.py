"""`ago prompts ...`: build and inspect prompt banks (no torch).

build FILE -o BANK     encode a prompt file's phrases into a bank (.npz); --bundle B: with the bundle's own
                       text encoder (a CLIP bundle's tower too, no torch); --text-encoder DIR: a CLIP folder (torch)
show BANK|FILE         classes, phrases, and the class-to-class similarity table
(`prompts export-encoder` and `prompts noise` need torch: ago_train/text/cli.py adds them to the group
`prompts_group(app)` gives.)
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def build(prompt_file: str = typer.Argument(..., help="prompt file, or a shipped name: cw, ow, ow_pretrain, veon_9_8 ..."),
          output: Path = typer.Option(..., "-o", "--output", help="bank file to write (.npz)"),
          encoder: str = typer.Option("onnx", "--encoder", help="onnx | int8 | torch | PATH to an ONNX text encoder"),
          text_encoder: Optional[Path] = typer.Option(None, "--text-encoder", help="a CLIP save_pretrained folder: "
                                                      "encode with its text tower (needs the training and vlm extras; "
                                                      "docs/prompts.md)"),
          bundle: Optional[Path] = typer.Option(None, "--bundle", help="a bundle folder: encode with the bundle's own "
                                                "text encoder (no torch), and check the bank fits the bundle"),
          template: Optional[str] = typer.Option(None, "--template", help="phrase template with one {} "
                                                 "(default: the measured winner, see docs/prompts.md)")):
    """Encode a prompt file's phrases into a prompt bank."""
    from ago_runtime.errors import AgoInputError
    from ago_runtime.vocab.bank import DEFAULT_TEMPLATE, build_bank, check_template
    from ago_runtime.outputs import check_output_file
    from ago_runtime.vocab.prompts import parse_prompt_file
    from ago_runtime.vocab.model_folder import clip_text_encoder
    from ago_runtime.vocab.text_encoder import bundle_text_encoder, text_encoder_for

    chosen = [o for o, given in (("--encoder", encoder != "onnx"), ("--text-encoder", text_encoder is not None),
                                 ("--bundle", bundle is not None)) if given]
    if len(chosen) > 1:
        raise AgoInputError(chosen[0], f"and {chosen[1]} both choose the text encoder; give one")
    space = parse_prompt_file(prompt_file)
    if template is not None:
        check_template(template, "--template")
    check_output_file(output, "-o")   # before the encoding
    loaded = None
    if bundle is not None:
        from ago_runtime.predict.bundle import Bundle

        loaded = Bundle.load(bundle)
        enc = bundle_text_encoder(loaded)
    elif text_encoder is not None:
        enc = clip_text_encoder(text_encoder)
    else:
        enc = text_encoder_for(encoder)
    bank = build_bank(space, enc, template if template is not None else DEFAULT_TEMPLATE)
    if loaded is not None:
        from ago_runtime.predict.contract import check_bank_fits

        check_bank_fits(bank, loaded.contract.text_encoder, prompt_file)   # the class count `ago infer` writes
    bank.save(output)
    typer.echo(f"{output}: {bank.num_classes} classes, {bank.num_phrases} phrases, "
               f"{bank.encoder_id} ({bank.encoder_variant}), dim {bank.dim}, template {bank.template!r}")


def show(bank_or_file: str = typer.Argument(..., help="a bank (.npz) or a prompt file / shipped name"),
         encoder: str = typer.Option("onnx", "--encoder", help="encoder for a prompt file (see build)")):
    """Print classes, phrases and the class similarity table (max cosine over phrase pairs)."""
    import numpy as np

    from ago_runtime.vocab.bank import PromptBank, build_bank
    from ago_runtime.vocab.prompts import parse_prompt_file
    from ago_runtime.vocab.text_encoder import text_encoder_for

    if bank_or_file.endswith(".npz"):
        bank = PromptBank.load(bank_or_file)
    else:
        bank = build_bank(parse_prompt_file(bank_or_file), text_encoder_for(encoder))
    echo = typer.echo
    echo(f"label space {bank.label_space!r}: {bank.num_classes} classes, {bank.num_phrases} phrases; "
         f"encoder {bank.encoder_id} ({bank.encoder_variant}, dim {bank.dim}, "
         f"weights sha256 {bank.encoder_hash[:12]}); template {bank.template!r}")
    table = bank.class_table
    known = bank.known_mask()
    width = max(len(n) for n in bank.class_names)
    echo(f"\n{'#':>3}  {'class':<{width}}  known  {table.name} -> phrases")
    for k, name in enumerate(bank.class_names):
        occ = ", ".join(table.name_of(i) for i in bank.occ3d_ids[k]) or "(open vocabulary)"
        phr = ", ".join(p for p, c in zip(bank.phrases, bank.phrase_class) if c == k)
        echo(f"{k:>3}  {name:<{width}}  {'yes' if known[k] else 'no ':<5}  [{occ}] -> {phr}")
    sim = bank.class_similarity()
    echo("\nclass similarity (max cosine over phrase pairs; * = most similar other class)")
    echo(" " * (width + 5) + "".join(f"{j:>6}" for j in range(bank.num_classes)))
    for k, name in enumerate(bank.class_names):
        others = np.delete(sim[k], k)
        best = others.max() if others.size else None
        cells = "".join(f"{sim[k, j]:>5.2f}{'*' if j != k and sim[k, j] == best else ' '}"
                        for j in range(bank.num_classes))
        echo(f"{k:>3}  {name:<{width}}{cells}")


def prompts_group(app: typer.Typer) -> typer.Typer:
    """The `ago prompts` group of `app` (with build and show), added to `app` the first time it is asked for:
    this module's register and ago_train/text/cli.py's both add their verbs to it."""
    for info in app.registered_groups:
        if info.name == "prompts":
            return info.typer_instance
    from ago_runtime.cli import verb_group

    group = verb_group("Prompt files, prompt banks and the text encoder.")
    group.command("build")(build)
    group.command("show")(show)
    app.add_typer(group, name="prompts")
    return group


def register(app: typer.Typer) -> None:
    prompts_group(app)
