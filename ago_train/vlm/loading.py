"""Hugging Face `save_pretrained` folders loaded offline, quietly, on the chosen device.

Everything here runs before any output is written: a folder that is missing, holds another architecture, has no
safetensors weights, cannot be loaded into its own config, or whose tokenizer does not fit the model is one
`AgoInputError` naming the option (`--detector`, `--sam`, `--clip`) and the published checkpoints that fit
(`ago_runtime.vocab.model_folder.ARCHITECTURES`).

transformers' own output (logging, loading bars, warnings) is switched off before it is imported
(`quiet_transformers`), and `HF_HUB_OFFLINE=1` makes a wrong path a local error, never a download.
"""

from __future__ import annotations

import os
import warnings
from enum import Enum
from pathlib import Path

from ago_runtime.errors import AgoInputError, MissingExtra
from ago_runtime.vocab.model_folder import ARCHITECTURES, read_model_config

ENV = {"HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", "HF_HUB_DISABLE_PROGRESS_BARS": "1",
       "TRANSFORMERS_VERBOSITY": "error", "TOKENIZERS_PARALLELISM": "false", "HF_HUB_DISABLE_TELEMETRY": "1"}


def quiet_transformers():
    """Import transformers offline with its logging, progress bars and warnings off; the module."""
    for key, value in ENV.items():
        os.environ[key] = value
    try:
        import transformers
    except ImportError:
        raise MissingExtra("this command needs the vlm extra (transformers): bash scripts/setup.sh --vlm "
                           "(or pip install -e '.[vlm]')") from None
    transformers.utils.logging.set_verbosity_error()
    transformers.utils.logging.disable_progress_bar()
    for module in ("transformers", "huggingface_hub", "tokenizers", "torch"):
        warnings.filterwarnings("ignore", module=module)
    return transformers


class TorchDevice(str, Enum):
    """`--device` of the verbs that run the 2D models (vlm-files, pseudo-labels --segmenter grounded-sam ...)."""
    CPU = "cpu"
    CUDA = "cuda"


def resolve_device(device: str):
    """`--device cpu|cuda` -> torch.device; cuda without a GPU is one error line."""
    import torch

    device = getattr(device, "value", device)
    if device not in ("cpu", "cuda"):
        raise AgoInputError("--device", f"expected cpu or cuda, got {device!r}")
    if device == "cuda" and not torch.cuda.is_available():
        raise AgoInputError("--device", "cuda was asked for but torch sees no GPU (torch.cuda.is_available() is "
                            "False); use --device cpu")
    if device == "cpu":
        # subnormal floats (SAM's zero padding drives activations there) make CPU matmuls many times slower
        # (benchmarks/results/vlm_cost.md)
        torch.set_flush_denormal(True)
    return torch.device(device)


def load_model(model_class, folder: str | Path, option: str, model_type: str, device, **from_pretrained):
    """`model_class.from_pretrained(folder, **from_pretrained)` (local files only, safetensors only) in eval mode on
    `device` (e.g. `config=` a sub-config: the CLIP text tower of ago_train/text/clip.py).

    A folder whose weights do not fill the model its config describes (missing or wrongly shaped tensors) is
    refused: a half-random model would run and give noise."""
    expected = f"expected a save_pretrained folder of {ARCHITECTURES[model_type]}"
    read_model_config(folder, option, model_type)
    quiet_transformers()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            model, info = model_class.from_pretrained(str(folder), local_files_only=True, use_safetensors=True,
                                                      output_loading_info=True, **from_pretrained)
        except (OSError, ValueError, RuntimeError, KeyError, TypeError) as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else e.__class__.__name__
            raise AgoInputError(option, f"{folder}: cannot be loaded ({first}); {expected}") from None
    bad = list(info.get("missing_keys") or []) + [str(m) for m in (info.get("mismatched_keys") or [])]
    if bad:
        raise AgoInputError(option, f"{folder}: its weights do not fill the model of its config.json ({len(bad)} "
                            f"tensors missing or of another shape, e.g. {bad[0]}); {expected}")
    return model.to(device).eval()


def preprocessor_config(folder: str | Path) -> dict:
    """The folder's preprocessor_config.json (resize sizes, mean, std), {} when it has none."""
    from ago_runtime.readers import read_json

    path = Path(folder) / "preprocessor_config.json"
    if not path.is_file():
        return {}
    cfg = read_json(path)
    if not isinstance(cfg, dict):
        raise AgoInputError(path, "expected a JSON object")
    return cfg


def mean_std(cfg: dict, default_mean, default_std, source) -> tuple[list[float], list[float]]:
    """image_mean / image_std of a preprocessor config (3 numbers each), else the architecture's defaults."""
    mean, std = cfg.get("image_mean", default_mean), cfg.get("image_std", default_std)
    for name, v in (("image_mean", mean), ("image_std", std)):
        if not (isinstance(v, (list, tuple)) and len(v) == 3 and all(isinstance(x, (int, float)) for x in v)):
            raise AgoInputError(source, f"{name} must be 3 numbers, got {v!r}")
    if min(std) <= 0:
        raise AgoInputError(source, f"image_std must be positive, got {std}")
    return [float(x) for x in mean], [float(x) for x in std]


def to_tensor(image_rgb, width: int, height: int, mean, std, device):
    """(H, W, 3) uint8 RGB -> (1, 3, height, width) float32, resized bilinearly, scaled to [0, 1], normalised."""
    import cv2
    import numpy as np
    import torch

    if image_rgb.shape[1] != width or image_rgb.shape[0] != height:
        image_rgb = cv2.resize(image_rgb, (width, height), interpolation=cv2.INTER_LINEAR)
    x = (image_rgb.astype(np.float32) / 255.0 - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))[None].to(device)
