"""MaskCLIP's dense read-out of a CLIP vision tower (`--clip DIR`): one C-d feature per image patch.

MaskCLIP (Zhou et al., ECCV 2022) reads CLIP's image-text space per patch without training: the last transformer
block's attention is replaced by its value path. Here, for an image resized to `width` x (width * H / W rounded to a
whole number of patches):

    tokens  = pre_layernorm(patch embedding + class token + position embeddings interpolated (bicubic) to the grid)
    tokens  = blocks 1 .. L-1 (unchanged)
    dense   = out_proj(v_proj(layer_norm1(tokens)))        the last block's value embeddings, no q/k, no MLP
    feature = visual_projection(post_layernorm(dense))     per patch token (the class token dropped)

giving a (C, h, w) map, C = the projection width (512 for ViT-B/16), h x w = the patch grid: stride = the patch size
in input pixels (16 for ViT-B/16), so a 1600 x 900 nuScenes image at the default width 768 gives 512 x 27 x 48
(the input GaussTR's MaskCLIP script uses). Maps are never made at full image resolution (512 x 900 x 1600 floats
is 1.5 GB an image): `ago pseudo-labels` samples them bilinearly at each LiDAR point's projection. The features are
written as computed (not L2-normalised), float16. (The paper upsamples MaskCLIP+ features with FeatUp; neither
MaskCLIP+'s distilled head nor FeatUp is here.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ago_runtime.errors import AgoInputError

from .loading import load_model, mean_std, preprocessor_config, quiet_transformers, to_tensor

OPENAI_CLIP_MEAN = [0.48145466, 0.4578275, 0.40821073]
OPENAI_CLIP_STD = [0.26862954, 0.26130258, 0.27577711]
DEFAULT_WIDTH = 768   # model input width; height follows the image's aspect (432 for 1600 x 900)


class MaskClip:
    option = "--clip"

    def __init__(self, folder: str | Path, device, width: int = DEFAULT_WIDTH, model=None):
        """Loads the folder's CLIP; `model` given: that one (benchmarks/vlm_cost.py; no encoder_id)."""
        quiet_transformers()
        from transformers import CLIPModel

        from ago_runtime.vocab.model_folder import clip_encoder_id

        self.folder = Path(folder)
        loaded = model is None
        model = load_model(CLIPModel, folder, self.option, "clip", device) if loaded else model
        # the image side only (the text tower is freed): CLIPVisionModelWithProjection would read the projection
        # width from vision_config, which a CLIPModel's config need not set
        self.vision, self.projection = model.vision_model, model.visual_projection
        del model
        self.device = device
        vcfg = self.vision.config
        self.patch = int(vcfg.patch_size)
        if width < self.patch or width % self.patch:
            raise AgoInputError("--clip-width", f"expected a multiple of the CLIP patch size {self.patch}, got {width}")
        self.width = int(width)
        self.channels = int(self.projection.out_features)
        self.mean, self.std = mean_std(preprocessor_config(folder) if loaded else {}, OPENAI_CLIP_MEAN,
                                       OPENAI_CLIP_STD, self.folder / "preprocessor_config.json")
        self.encoder_id = clip_encoder_id(folder) if loaded else None

    def input_size(self, height: int, width: int) -> tuple[int, int]:
        """(h, w) model input for an image of that size: `self.width` wide, whole patches, the image's aspect."""
        rows = max(1, int(round(self.width * height / width / self.patch)))
        return rows * self.patch, self.width

    def meta(self) -> dict:
        return {"channels": self.channels, "stride": self.patch, "input_width": self.width,
                "model": f"MaskCLIP read-out (last block's value path) of the CLIP in {self.folder.resolve()}",
                "encoder_id": self.encoder_id, "normalised": False}

    def features(self, image_rgb: np.ndarray) -> np.ndarray:
        """(C, h, w) float16 dense features of an (H, W, 3) uint8 RGB image."""
        import torch

        H, W = image_rgb.shape[:2]
        ih, iw = self.input_size(H, W)
        pixels = to_tensor(image_rgb, iw, ih, self.mean, self.std, self.device)
        vision = self.vision
        with torch.inference_mode():
            tokens = vision.embeddings(pixels, interpolate_pos_encoding=True)
            tokens = vision.pre_layrnorm(tokens)
            layers = vision.encoder.layers
            for layer in layers[:-1]:
                tokens = layer(tokens, None)
                tokens = tokens[0] if isinstance(tokens, tuple) else tokens
            last = layers[-1]
            dense = last.self_attn.out_proj(last.self_attn.v_proj(last.layer_norm1(tokens)))
            feats = self.projection(vision.post_layernorm(dense))[0, 1:]   # (h*w, C)
        h, w = ih // self.patch, iw // self.patch
        return feats.float().cpu().numpy().T.reshape(self.channels, h, w).astype(np.float16)
