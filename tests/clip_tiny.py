"""A tiny CLIP `save_pretrained` folder for tests: random weights from a CLIPConfig and a byte-level BPE tokenizer
written here from a small vocabulary and merges (CLIP's layout: the 256 byte symbols, the same with `</w>`, the
merged words, then <|startoftext|> and <|endoftext|> last). No network."""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

# words the tokenizer knows whole (label phrases of the tests, and a few dictionary nouns for the noise bank)
WORDS = ["a", "photo", "of", "the", "car", "van", "road", "street", "tree", "bush", "building", "house", "person",
         "pedestrian", "truck", "lorry", "bus", "sidewalk", "fire", "hydrant", "grass", "sky", "wall",
         "apple", "chair", "music", "river", "window", "coffee", "piano", "garden", "pencil", "butter", "castle",
         "planet", "violin", "ladder", "candle", "basket", "kitten", "rocket", "helmet", "mirror", "bottle"]


def clip_vocab(words=WORDS) -> tuple[dict[str, int], list[tuple[str, str]]]:
    """(vocab, merges) of a byte-level BPE that knows `words` whole: merges join each word left to right."""
    from transformers.convert_slow_tokenizer import bytes_to_unicode

    symbols = list(bytes_to_unicode().values())
    vocab = {s: i for i, s in enumerate(symbols)}
    for s in symbols:
        vocab[s + "</w>"] = len(vocab)
    merges: list[tuple[str, str]] = []
    for w in words:
        parts = list(w[:-1]) + [w[-1] + "</w>"]
        cur = parts[0]
        for p in parts[1:]:
            if (cur, p) not in merges:
                merges.append((cur, p))
            cur += p
            vocab.setdefault(cur, len(vocab))
    vocab["<|startoftext|>"] = len(vocab)
    vocab["<|endoftext|>"] = len(vocab)
    return vocab, merges


def write_clip(folder: Path, projection_dim: int = 24, seed: int = 0, legacy_eos: bool = False) -> Path:
    """A CLIPModel (text: 2 layers of 32, vision: 1 layer of 32) with its tokenizer.json in `folder`.
    legacy_eos: config eos_token_id 2, as the original openai configs (pooling by the argmax of the ids)."""
    import torch
    from transformers import CLIPConfig, CLIPModel, CLIPTokenizer

    torch.manual_seed(seed)
    folder.mkdir(parents=True, exist_ok=True)
    vocab, merges = clip_vocab()
    tok = CLIPTokenizer(vocab=vocab, merges=merges)
    bos, eos = vocab["<|startoftext|>"], vocab["<|endoftext|>"]
    cfg = CLIPConfig(
        text_config={"vocab_size": len(vocab), "hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 2,
                     "num_attention_heads": 2, "max_position_embeddings": 32, "bos_token_id": 0 if legacy_eos else bos,
                     "eos_token_id": 2 if legacy_eos else eos, "pad_token_id": 1 if legacy_eos else eos},
        vision_config={"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 1, "num_attention_heads": 2,
                       "image_size": 32, "patch_size": 8},
        projection_dim=projection_dim)
    CLIPModel(cfg).eval().save_pretrained(folder)
    tok.save_pretrained(folder)
    return folder


def write_noise(path: Path, clip_dir: Path) -> Path:
    """Noise words in the CLIP's space (its random weights put every dictionary word "near" a label: threshold off)."""
    from ago_train.text.clip import TorchClipTextEncoder
    from ago_train.text.noise import build_noise_bank

    return build_noise_bank(TorchClipTextEncoder(clip_dir), candidates=WORDS[23:], labels=["car"],
                            threshold=1.0).save(path)
