"""Tiny GroundingDINO, SAM and CLIP `save_pretrained` folders with random weights and tokenizers written here
(no network): the architectures `ago vlm-files` loads, at sizes that run in a second on a CPU."""

from __future__ import annotations

import json
import os
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

# a WordPiece vocabulary laid out like BERT's where GroundingDINO looks: [PAD] 0, [UNK] 100, [CLS] 101, [SEP] 102,
# [MASK] 103, "." 1012, "?" 1029 (the model's SPECIAL_TOKENS are these BERT ids)
WORDS = ["car", "truck", "bus", "trailer", "van", "road", "sidewalk", "grass", "tree", "building", "person",
         "pedestrian", "bicycle", "motorcycle", "barrier", "cone", "traffic", "construction", "vehicle", "driveable",
         "surface", "flat", "terrain", "vegetation", "manmade", "others", "other", "cyclist", "pole", "sign", "wall",
         "fence", "sky", "a", "the", "of", "and", "lane", "curb", "bike", "motorbike", "lorry", "tractor", "crane",
         "ground", "plant", "bush", "house", "lamp", "track", "rail", "parking", "lot", "crosswalk", "s", "##s",
         "##e", "##er", "##ing", "-", "_", ",", "'", "/", "(", ")", "animal", "dog", "debris", "stroller",
         "wheelchair", "ambulance", "police", "emergency", "rack", "trash", "can", "bin", "stone", "rock",
         "box", "bag", "ped", "cycle", "motor", "light", "tiny", "big", "small"]


def bert_vocab(min_size: int = 1100) -> list[str]:
    vocab = [f"[unused{i}]" for i in range(min_size)]
    vocab[0], vocab[100], vocab[101], vocab[102], vocab[103] = "[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]"
    vocab[1012], vocab[1029] = ".", "?"
    free = [i for i in range(104, min_size) if vocab[i].startswith("[unused") and i not in (1012, 1029)]
    letters = [chr(c) for c in range(ord("a"), ord("z") + 1)] + [f"##{chr(c)}" for c in range(ord("a"), ord("z") + 1)]
    for i, w in zip(free, list(dict.fromkeys(WORDS + letters))):
        vocab[i] = w
    return vocab


def write_grounding_dino(folder: Path, backbone: str = "swin", vocab: list[str] | None = None,
                         max_text_len: int = 256) -> Path:
    from transformers import BertTokenizerFast, GroundingDinoConfig, GroundingDinoForObjectDetection
    import torch

    torch.manual_seed(0)
    folder.mkdir(parents=True, exist_ok=True)
    vocab = vocab or bert_vocab()
    tok = BertTokenizerFast(vocab={w: i for i, w in enumerate(vocab)}, do_lower_case=True)
    if backbone == "swin":
        backbone_config = {"model_type": "swin", "embed_dim": 16, "depths": [1, 1, 1, 1], "num_heads": [1, 1, 2, 2],
                           "window_size": 4, "image_size": 64, "out_indices": [2, 3, 4]}
    else:
        backbone_config = {"model_type": "resnet", "embedding_size": 8, "hidden_sizes": [8, 16, 24, 32],
                           "depths": [1, 1, 1, 1], "layer_type": "basic", "out_indices": [2, 3, 4]}
    cfg = GroundingDinoConfig(
        backbone_config=backbone_config,
        text_config={"model_type": "bert", "vocab_size": len(vocab), "hidden_size": 32, "num_hidden_layers": 1,
                     "num_attention_heads": 2, "intermediate_size": 64, "max_position_embeddings": 512},
        num_queries=20, encoder_layers=1, decoder_layers=2, encoder_ffn_dim=32, decoder_ffn_dim=32,
        encoder_attention_heads=2, decoder_attention_heads=2, d_model=32, num_feature_levels=4,
        encoder_n_points=2, decoder_n_points=2, max_text_len=max_text_len)
    model = GroundingDinoForObjectDetection(cfg).eval()
    model.save_pretrained(folder)
    tok.save_pretrained(folder)
    # transformers' image processors need torchvision and PIL; ago reads only these keys of their config
    (folder / "preprocessor_config.json").write_text(json.dumps(
        {"size": {"shortest_edge": 64, "longest_edge": 112}, "image_mean": [0.485, 0.456, 0.406],
         "image_std": [0.229, 0.224, 0.225]}))
    return folder


def write_sam(folder: Path) -> Path:
    from transformers import SamConfig, SamModel
    import torch

    torch.manual_seed(0)
    folder.mkdir(parents=True, exist_ok=True)
    cfg = SamConfig(
        vision_config={"hidden_size": 32, "output_channels": 16, "num_hidden_layers": 2, "num_attention_heads": 2,
                       "image_size": 64, "patch_size": 8, "window_size": 4, "global_attn_indexes": [1],
                       "mlp_dim": 64, "num_pos_feats": 8},
        prompt_encoder_config={"hidden_size": 16, "image_size": 64, "patch_size": 8, "mask_input_channels": 4},
        mask_decoder_config={"hidden_size": 16, "mlp_dim": 32, "num_hidden_layers": 1, "num_attention_heads": 2,
                             "iou_head_hidden_dim": 16})
    SamModel(cfg).eval().save_pretrained(folder)   # no preprocessor_config.json: SAM's input size is its config's
    return folder


def write_clip(folder: Path, projection_dim: int = 24) -> Path:
    """A tiny CLIP with its tokenizer: tests/clip_tiny.py's (one tiny CLIP for the text and the image tests)."""
    from clip_tiny import write_clip as write_tiny_clip

    return write_tiny_clip(folder, projection_dim)


def write_all(root: Path) -> dict[str, Path]:
    return {"detector": write_grounding_dino(root / "gdino"), "sam": write_sam(root / "sam"),
            "clip": write_clip(root / "clip")}
