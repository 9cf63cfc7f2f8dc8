"""A bundle's own text encoder: the CLIP text tower a checkpoint was trained with, as ONNX, parity-checked.

A checkpoint whose bank was made by a CLIP folder (`ago train --text-encoder DIR`: bank encoder_id "clip:<hex>")
cannot take its new prompt files to MiniLM, so `ago export` ships the folder's text tower in the bundle:

    text_encoder.onnx              input_ids, attention_mask (int64, batch x sequence) -> embeddings (batch, D):
                                   CLIP's pooled projection (get_text_features), normalised by the runtime
    text_encoder.json              sidecar: encoder id, variant, pooling "eos", max length, what the tower is
    text_encoder.tokenizer.json    the folder's tokenizer.json (BPE; read by the `tokenizers` library)

so `ago infer --prompts NEW.txt` and `ago prompts build NEW.txt --bundle B` encode new phrases with the
bundle's own tower, without torch (ago_runtime.vocab.text_encoder.bundle_text_encoder).

The folder: `ago export --text-encoder DIR`, else the checkpoint's train_config text_encoder; its id must be the
bank's (one line naming both otherwise).

Parity (export refuses to write a bundle that fails): on the training bank's phrases (with its template) and a
few probes (the empty text, a text longer than the context), the ONNX tower's normalised embeddings against
transformers' `get_text_features` on the same tokens, and against the checkpoint's bank itself:
    fp32: min cosine >= TEXT_FP32_MIN_COS (1 - 1e-5)
    int8 (`--int8`): the tower's MatMul/Gemm weights quantised dynamically (ago_export.quantize); shipped
          instead of fp32 only when its min cosine >= TEXT_INT8_MIN_COS (0.995, the worst MiniLM int8 cosine
          measured on real words was 0.997: docs/prompts.md); otherwise fp32 ships and bundle.json says why.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.vocab.bank import PromptBank, apply_template
from ago_runtime.vocab.model_folder import check_same_encoder, clip_encoder_id, read_model_config
from ago_runtime.vocab.text_encoder import BUNDLE_ENCODER_NAME, OnnxTextEncoder, l2_normalise

TEXT_FP32_MIN_COS = 1 - 1e-5
TEXT_INT8_MIN_COS = 0.995
PROBES = ["", "a", "a photo of a car", "a traffic cone on the road", " ".join(["road"] * 100)]


def is_clip_bank(bank: PromptBank) -> bool:
    return bank.encoder_id.startswith("clip:")


def clip_folder_for(trained_with: str | None, checkpoint, bank: PromptBank, folder: str | Path | None) -> Path:
    """The CLIP folder to export the tower of: `folder` (--text-encoder) or `trained_with`, the checkpoint's
    train_config text_encoder (`CheckpointContract.text_encoder`); checked to be the folder that made the
    checkpoint's bank."""
    option = "--text-encoder"
    if folder is None:
        folder = trained_with
        option = f"{checkpoint} (train_config text_encoder)"
        if folder is None or not Path(folder).is_dir():
            where = "" if folder is None else f" from {folder}, which is not there"
            raise AgoInputError("--text-encoder", f"{checkpoint} was trained with the CLIP text encoder "
                                f"{bank.encoder_id}{where}; give its folder: --text-encoder DIR")
    read_model_config(folder, option, "clip")
    check_same_encoder("the checkpoint's prompt bank", bank.encoder_id, f"the CLIP folder {folder}",
                       clip_encoder_id(folder), source=option)
    return Path(folder)


def _agreement(got: np.ndarray, ref: np.ndarray) -> dict:
    cos = (l2_normalise(got) * l2_normalise(ref)).sum(axis=1)
    return {"min_cosine": float(cos.min()), "mean_cosine": float(cos.mean()),
            "max_abs": float(np.abs(l2_normalise(got) - l2_normalise(ref)).max()), "phrases": int(len(cos))}


def check_tower(path: Path, phrases: list[str], reference: np.ndarray, bank: PromptBank, min_cos: float,
                tokenizer=None) -> dict:
    """The ONNX tower at `path` (tokenised as its sidecar says, or by `tokenizer`) against transformers
    (`reference`, on `phrases`) and against the training bank (its first rows are the bank's phrases):
    {"transformers": ..., "bank": ..., "min_cosine_allowed", "ok"}."""
    got = OnnxTextEncoder(path, pooling="eos", tokenizer=tokenizer).encode(phrases)
    report = {"transformers": _agreement(got, reference),
              "bank": _agreement(got[: bank.num_phrases], bank.embeddings), "min_cosine_allowed": min_cos}
    report["ok"] = bool(min(report["transformers"]["min_cosine"], report["bank"]["min_cosine"]) >= min_cos)
    return report


def describe(report: dict) -> str:
    t, b = report["transformers"], report["bank"]
    return (f"min cosine {t['min_cosine']:.6f} to transformers' get_text_features over {t['phrases']} phrases, "
            f"{b['min_cosine']:.6f} to the checkpoint's bank (allowed >= {report['min_cosine_allowed']})")


def export_text_tower(folder: Path, out_dir: Path, bank: PromptBank, int8: bool, checkpoint, log=print) -> dict:
    """Write text_encoder.onnx (+ sidecar, tokenizer) of the CLIP in `folder` into `out_dir` and check it (module
    docstring). Returns {"files": {key: name}, "parity": report, "card": what the card says of the encoder}."""
    import warnings

    from ago_train.text.clip import TorchClipTextEncoder, export_clip_onnx, write_clip_sidecar

    from .quantize import quantize_encoder

    torch_encoder = TorchClipTextEncoder(folder, "--text-encoder")
    path = out_dir / BUNDLE_ENCODER_NAME
    log(f"exporting the CLIP text tower {torch_encoder.encoder_id} to ONNX ...")
    export_clip_onnx(torch_encoder, path)
    phrases = [apply_template(bank.template, p) for p in bank.phrases] + PROBES
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # the long probe is cut to the context on both sides
        reference = torch_encoder.raw(phrases)
        report = {"fp32": check_tower(path, phrases, reference, bank, TEXT_FP32_MIN_COS)}
    log(f"text encoder parity fp32: {describe(report['fp32'])}")
    if not report["fp32"]["ok"]:
        raise AgoInputError(checkpoint, f"text encoder parity check failed: {describe(report['fp32'])}")
    variant = "onnx-fp32"
    if int8:
        q = out_dir / "text_encoder.int8.onnx"
        quantize_encoder(path, q)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            report["int8"] = check_tower(q, phrases, reference, bank, TEXT_INT8_MIN_COS, torch_encoder.tokenizer)
        log(f"text encoder parity int8: {describe(report['int8'])}")
        if report["int8"]["ok"]:
            os.replace(q, path)
            variant = "onnx-int8"
        else:
            q.unlink()
            report["int8"]["note"] = "int8 text tower outside the tolerance: the fp32 tower ships"
            log("note: the int8 text tower is outside the tolerance; the fp32 tower ships")
    report["shipped"] = variant
    card = {"id": torch_encoder.encoder_id, "variant": variant, "dim": torch_encoder.dim,
            "folder": str(Path(folder).resolve()), **torch_encoder.describe()}
    if variant != "onnx-fp32":
        write_clip_sidecar(torch_encoder, path, variant)
    files = {"text_encoder": path.name, "text_encoder_sidecar": path.with_suffix(".json").name,
             "text_encoder_tokenizer": f"{path.stem}.tokenizer.json"}
    return {"files": files, "parity": report, "card": card}
