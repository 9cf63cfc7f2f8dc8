"""Hugging Face model folders the user already has (`save_pretrained` layout), checked and named without torch.

A folder holds `config.json` and its weights (`model.safetensors`, or shards `model-0000K-of-0000N.safetensors`;
`pytorch_model.bin` is refused: it is a pickle). The same CLIP folder gives the text tower (issue T: prompt banks)
and the image tower (issue M: MaskCLIP features), so both name it the same way:

    encoder_id = "clip:<16 hex>"   the sha256 over config.json's bytes and every weight file's bytes, in name order

A bank, a feature folder's `meta.json`, a checkpoint and a bundle that carry the same `encoder_id` were made by
the same weights; two that differ are refused with one `error:` line naming both (`check_same_encoder`).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from ago_runtime.errors import AgoInputError
from ago_runtime.vocab.text_encoder import extra_encoder, file_sha256

CONFIG_NAME = "config.json"
# model types of the architectures ago loads, and the published checkpoints each folder may hold (said in errors)
ARCHITECTURES = {
    "clip": "CLIP ViT-B/16 (openai/clip-vit-base-patch16) or another CLIP",
    "grounding-dino": "GroundingDINO tiny or base (IDEA-Research/grounding-dino-tiny, -base)",
    "sam": "SAM ViT-B/L/H (facebook/sam-vit-base, -large, -huge)",
}
MAX_CONFIG_BYTES = 1 << 20   # a config.json is a few kB; never read a huge one


def weight_files(folder: Path) -> list[Path]:
    """The folder's safetensors weight files, in name order (empty when there are none)."""
    return sorted(p for p in folder.glob("*.safetensors") if p.is_file())


def read_model_config(folder: str | Path, option: str, model_type: str) -> dict:
    """config.json of a `save_pretrained` folder of `model_type` ("clip", "grounding-dino", "sam").

    Raises AgoInputError naming `option` (e.g. "--clip") when the folder is missing, has no config.json or
    no safetensors weights, or holds another architecture; the message names the model ids that fit."""
    if model_type not in ARCHITECTURES:
        raise ValueError(f"unknown model type {model_type!r}")
    folder = Path(folder)
    expected = f"expected a save_pretrained folder of {ARCHITECTURES[model_type]}"
    if not folder.is_dir():
        raise AgoInputError(option, f"{folder}: no such folder; {expected}")
    cfg_path = folder / CONFIG_NAME
    if not cfg_path.is_file():
        raise AgoInputError(option, f"{folder}: no {CONFIG_NAME}; {expected}")
    if cfg_path.stat().st_size > MAX_CONFIG_BYTES:
        raise AgoInputError(option, f"{cfg_path}: larger than {MAX_CONFIG_BYTES} bytes; not a model config")
    try:
        cfg = json.loads(cfg_path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise AgoInputError(option, f"{cfg_path}: not JSON ({e})") from None
    if not isinstance(cfg, dict):
        raise AgoInputError(option, f"{cfg_path}: not a JSON object; {expected}")
    found = cfg.get("model_type")
    if found != model_type:
        raise AgoInputError(option, f"{folder}: holds a {found!r} model; {expected}")
    if not weight_files(folder):
        bin_note = " (pytorch_model.bin is a pickle and is not read: save with safe_serialization=True)" \
            if (folder / "pytorch_model.bin").exists() else ""
        raise AgoInputError(option, f"{folder}: no *.safetensors weights{bin_note}; {expected}")
    return cfg


def folder_hash(folder: str | Path) -> str:
    """sha256 hex over config.json's bytes and each weight file's sha256, in name order."""
    folder = Path(folder)
    h = hashlib.sha256()
    h.update((folder / CONFIG_NAME).read_bytes())
    for p in weight_files(folder):
        h.update(p.name.encode())
        h.update(file_sha256(p).encode())
    return h.hexdigest()


def clip_encoder_id(folder: str | Path) -> str:
    """The id a bank, feature folder, checkpoint and bundle record for the CLIP in `folder`: "clip:<16 hex>"."""
    return "clip:" + folder_hash(folder)[:16]


def check_same_encoder(what_a: str, id_a: str, what_b: str, id_b: str, source=None) -> None:
    """One `error:` line when two things were made by different encoders, naming both (e.g. features vs bank)."""
    if id_a != id_b:
        raise AgoInputError(source, f"{what_a} were made with encoder {id_a!r} but {what_b} with {id_b!r}; "
                            "they must come from the same model")


def clip_text_encoder(folder: str | Path, option: str = "--text-encoder", verb: str = "prompts build"):
    """The text tower of the CLIP folder `folder`, in torch (ago_train.text.clip.TorchClipTextEncoder; needs the
    training and vlm extras): the folder is checked first (one `error:` line naming `option`), torch after."""
    read_model_config(folder, option, "clip")
    return extra_encoder("clip", folder, option, asked_by=f"{verb} {option} DIR")
