"""The text tower of a CLIP `save_pretrained` folder, in torch, and its ONNX export (the paper's text space).

Takes phrases (list[str]); gives L2-normalised float32 embeddings (N, D), D = the folder's `projection_dim`
(512 for ViT-B/16). The embedding is CLIP's pooled projection, what transformers' `get_text_features` gives:
the final layer norm's output at the end token (`<|endoftext|>`), times `text_projection`; ago then
L2-normalises it. It is the space MaskCLIP's dense image features are read out in (the visual projection),
so the modality adapter aligns to image features and voxels are scored against prompts in one space
(docs/prompts.md, "A CLIP text encoder").

The folder: config.json (model_type "clip"), *.safetensors (the full CLIPModel; only the text tower and
text_projection are loaded) and tokenizer.json. Tokenisation is ago_runtime.vocab.clip_tokenizer.ClipTokenizer
over that tokenizer.json, shared with the ONNX runtime path. Identity: encoder_id = clip_encoder_id(folder)
("clip:<16 hex>", ago_runtime.vocab.model_folder), weights_hash = the folder hash (config + weights).

Loaded offline (HF_HUB_OFFLINE=1 before transformers is imported), its logging and loading bars off; always
frozen (eval mode, no gradients). Needs the vlm extra (transformers).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch

from ago_runtime.errors import AgoInputError
from ago_runtime.vocab.clip_tokenizer import ClipTokenizer
from ago_runtime.vocab.model_folder import ARCHITECTURES, clip_encoder_id, folder_hash, read_model_config
from ago_train.vlm.loading import load_model, quiet_transformers   # one offline, quiet loader of HF folders

TOKENIZER_NAME = "tokenizer.json"
DEFAULT_MAX_LENGTH = 77        # CLIP's context length (its text position embeddings)
DEFAULT_PROJECTION = 512


def text_settings(cfg: dict) -> tuple[int, int]:
    """(projection width D, context length) of a CLIP config.json: top-level projection_dim (the text_config's own
    projection_dim is a default that save_pretrained writes, not the model's), text_config max_position_embeddings."""
    text = cfg.get("text_config") or {}
    return int(cfg.get("projection_dim", DEFAULT_PROJECTION)), int(text.get("max_position_embeddings", DEFAULT_MAX_LENGTH))


def load_clip_text_model(folder: str | Path, option: str = "--text-encoder"):
    """The folder's CLIPTextModelWithProjection (eager attention, frozen, CPU) and its config.json dict."""
    folder = Path(folder)
    cfg = read_model_config(folder, option, "clip")
    transformers = quiet_transformers()
    try:
        full = transformers.CLIPConfig.from_pretrained(str(folder), local_files_only=True)
    except (OSError, ValueError, KeyError, TypeError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else e.__class__.__name__
        raise AgoInputError(option, f"{folder}: cannot be loaded ({first}); expected a save_pretrained folder of "
                            f"{ARCHITECTURES['clip']}") from None
    text_cfg = full.text_config
    text_cfg.projection_dim = full.projection_dim
    # the text tower alone, from the whole CLIP's weights (the vision tower's tensors are left unread)
    model = load_model(transformers.CLIPTextModelWithProjection, folder, option, "clip", "cpu", config=text_cfg,
                       attn_implementation="eager")   # in eval mode
    for p in model.parameters():
        p.requires_grad_(False)
    return model, cfg


def folder_tokenizer(folder: str | Path, max_length: int, option: str = "--text-encoder") -> ClipTokenizer:
    path = Path(folder) / TOKENIZER_NAME
    if not path.is_file():
        raise AgoInputError(option, f"{folder}: no {TOKENIZER_NAME} (the CLIP tokenizer); save it beside the model: "
                            "CLIPTokenizer.from_pretrained(ID).save_pretrained(DIR)")
    return ClipTokenizer(path, max_length=max_length)


class TextTower(torch.nn.Module):
    """input_ids, attention_mask (B, L) int64 -> the pooled projected embedding (B, D), not normalised: what
    `CLIPModel.get_text_features` gives (transformers' own pooling at the end token)."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
        return self.model(input_ids=input_ids, attention_mask=attention_mask).text_embeds


class TorchClipTextEncoder:
    """Same interface as ago_runtime.vocab.text_encoder.OnnxTextEncoder: encode(list[str]) -> (N, D), normalised."""

    variant = "torch-fp32"

    def __init__(self, folder: str | Path, option: str = "--text-encoder", batch_size: int = 128):
        self.folder = Path(folder)
        model, cfg = load_clip_text_model(self.folder, option)
        self.tower = TextTower(model)
        self.dim, self.max_length = text_settings(cfg)
        self.tokenizer = folder_tokenizer(self.folder, self.max_length, option)
        if self.tokenizer.eos_id >= int(model.config.vocab_size):
            raise AgoInputError(option, f"{self.folder / TOKENIZER_NAME}: its end token id {self.tokenizer.eos_id} is "
                                f"outside the model's vocabulary ({model.config.vocab_size}); not this model's tokenizer")
        self.encoder_id = clip_encoder_id(self.folder)
        self.batch_size = batch_size
        self._hash = folder_hash(self.folder)

    @property
    def weights_hash(self) -> str:
        return self._hash

    @torch.no_grad()
    def raw(self, phrases: list[str]) -> np.ndarray:
        """float32 (N, D): get_text_features of `phrases`, not normalised (the parity reference)."""
        phrases = list(phrases)
        out = np.zeros((len(phrases), self.dim), dtype=np.float32)
        order = np.argsort([len(p) for p in phrases], kind="stable")
        for s in range(0, len(phrases), self.batch_size):
            idx = order[s:s + self.batch_size]
            ids, mask = self.tokenizer.encode([phrases[i] for i in idx])
            out[idx] = self.tower(torch.from_numpy(ids), torch.from_numpy(mask)).numpy()
        return out

    def encode(self, phrases: list[str]) -> np.ndarray:
        e = self.raw(phrases)
        return (e / np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-12)).astype(np.float32)

    def describe(self) -> dict:
        """What the bundle card and the ONNX sidecar say about this encoder."""
        text = self.tower.model.config
        return {"kind": "clip", "embedding": "pooled projection (get_text_features), L2-normalised",
                "hidden_size": int(text.hidden_size), "layers": int(text.num_hidden_layers),
                "projection_dim": self.dim, "max_length": self.max_length}


def export_clip_onnx(encoder: TorchClipTextEncoder, path: str | Path, opset: int = 17) -> Path:
    """Write the text tower as ONNX at `path`: inputs input_ids, attention_mask (int64, dynamic batch x sequence),
    output `embeddings` (batch, D), the pooled projection NOT normalised (OnnxTextEncoder normalises); plus the
    sidecar (PATH with .json: encoder id, pooling "eos", max length, tokenizer) and PATH-stem.tokenizer.json."""
    path = Path(path)
    ids, mask = encoder.tokenizer.encode(["a", "a photo of a car"])
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        torch.onnx.export(encoder.tower, (torch.from_numpy(ids), torch.from_numpy(mask)), str(path), dynamo=False,
                          opset_version=opset, input_names=["input_ids", "attention_mask"], output_names=["embeddings"],
                          dynamic_axes={"input_ids": {0: "batch", 1: "sequence"},
                                        "attention_mask": {0: "batch", 1: "sequence"}, "embeddings": {0: "batch"}},
                          do_constant_folding=True)
    write_clip_sidecar(encoder, path, "onnx-fp32")
    return path


def write_clip_sidecar(encoder: TorchClipTextEncoder, path: str | Path, variant: str) -> Path:
    """The sidecar of the exported tower at `path` (encoder id, `variant`, pooling "eos", context length, what the
    tower is) and its tokenizer.json copied beside it (PATH-stem.tokenizer.json)."""
    from ago_runtime.vocab.text_encoder import write_sidecar

    return write_sidecar(path, encoder_id=encoder.encoder_id, variant=variant, pooling="eos",
                         max_length=encoder.max_length, tokenizer_path=encoder.folder / TOKENIZER_NAME,
                         extra={"text_encoder": encoder.describe()})
