"""Value checks for training configs (`TrainConfig`, its `ModelConfig`), so that a bad `--set` or JSON
value is one clear error before any work instead of a traceback (or a silently wrong run) later.

`check_train_config(cfg, source)` gives `cfg` back or raises AgoInputError naming `source` (the JSON
file, or "--set" when the value came from the command line) and the key:
- types: integer keys hold integers (not strings, not booleans), float keys numbers, bool keys bools;
- ranges: lr > 0; weight_decay, warmup_lr, min_lr, grad_clip, noise_words, train_voxels,
  num_workers, seed >= 0; epochs, batch_size, log_every, ckpt_every >= 1; max_steps, max_frames
  None or >= 1; 0 <= warmup_max_fraction <= 1; 0 <= color_jitter < 1; min_lr <= lr; warmup_steps >= 0;
- voxel_sampling one of losses.sampling.SAMPLING_RULES, 0 < occupied_share < 1, feature_cache a non-empty
  string, snapshot_steps None or a list of steps >= 1, model.frozen_stages 0..3; quant one of
  quant.QUANT_MODES, and anything but "none" needs init_from;
- device: auto, cpu, cuda or cuda:N (`check_device`); amp one of ago_train.amp.AMP_MODES;
- model: every size (widths, layer and point counts, image size) an integer from 1 to its bound
  (`_model_bound`), model.grid by ago_runtime.geometry.grid.check_grid_dict.
"""

from __future__ import annotations

import math
import re

from ago_runtime.errors import AgoInputError

DEVICE_RE = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")

_INT_MIN = {"epochs": 1, "batch_size": 1, "log_every": 1, "ckpt_every": 1, "warmup_steps": 0,
            "noise_words": 0, "train_voxels": 0, "num_workers": 0, "seed": 0, "item_memory_mb": 0}
_OPTIONAL_INT_MIN = {"max_steps": 1, "max_frames": 1}
_FLOAT_MIN = {"weight_decay": 0.0, "warmup_lr": 0.0, "min_lr": 0.0, "grad_clip": 0.0, "backbone_lr_mult": 0.0,
              "fpn_lr_mult": 0.0}
_MODEL_POSITIVE = ("image_width", "image_height", "num_cameras", "tpv_dim", "num_heads", "num_layers",
                   "ffn_dim", "hidden_dim", "decoder_layers", "embed_dim", "adapter_depth", "adapter_hidden",
                   "num_points_in_pillar", "num_points_in_pillar_side", "num_sampling_offsets",
                   "cameras_per_query", "cameras_per_query_side", "num_cross_view_points", "num_self_points")
_MODEL_OPTIONAL_POSITIVE = ("tpv_h", "tpv_w", "tpv_z")
MAX_MODEL_LAYERS = 64          # encoder / decoder layers, attention heads
MAX_MODEL_POINTS = 256         # sampling points, offsets, cameras per query


def _model_bound(key: str) -> int:
    """The largest value a model size `key` may take: image sides as a bundle's (16384 pixels), cameras as a rig's,
    widths as a text embedding's (8192), layer and head counts MAX_MODEL_LAYERS, point counts MAX_MODEL_POINTS,
    TPV plane sizes the grid's (checked again against the grid by ModelConfig.validate)."""
    from ago_runtime.geometry.camera import MAX_CAMERAS
    from ago_runtime.geometry.grid import MAX_GRID_VOXELS
    from ago_runtime.predict.contract import MAX_EMBED_DIM, MAX_IMAGE_SIDE

    if key in ("image_width", "image_height"):
        return MAX_IMAGE_SIDE
    if key == "num_cameras":
        return MAX_CAMERAS
    if key in ("tpv_dim", "ffn_dim", "hidden_dim", "embed_dim", "adapter_hidden"):
        return MAX_EMBED_DIM
    if key in ("num_heads", "num_layers", "decoder_layers", "adapter_depth"):
        return MAX_MODEL_LAYERS
    if key in _MODEL_OPTIONAL_POSITIVE:
        return MAX_GRID_VOXELS
    return MAX_MODEL_POINTS


def check_device(spec, where: str = "--device") -> str:
    """`spec` when it is auto, cpu, cuda or cuda:N; else AgoInputError naming `where`."""
    if not isinstance(spec, str) or not DEVICE_RE.match(spec):
        raise AgoInputError(where, f"device must be auto, cpu, cuda or cuda:N, got {spec!r}")
    return spec


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return (isinstance(v, (int, float)) and not isinstance(v, bool)) and math.isfinite(v)


def _int(cfg, key: str, lo: int, source, optional: bool = False) -> None:
    v = getattr(cfg, key)
    if optional and v is None:
        return
    if not _is_int(v) or v < lo:
        raise AgoInputError(source, f"{key} must be an integer >= {lo}{' or null' if optional else ''}, got {v!r}")


def _num(cfg, key: str, lo: float, source, strict: bool = False, hi: float | None = None,
         hi_open: bool = False) -> None:
    v = getattr(cfg, key)
    ok = _is_number(v) and (v > lo if strict else v >= lo)
    if ok and hi is not None:
        ok = v < hi if hi_open else v <= hi
    if not ok:
        rng = f"{'>' if strict else '>='} {lo:g}" + (f" and {'<' if hi_open else '<='} {hi:g}" if hi is not None else "")
        raise AgoInputError(source, f"{key} must be a number {rng}, got {v!r}")


def check_model_config(model, source) -> None:
    """Types and ranges of a ModelConfig (from a --set, a JSON config or a checkpoint's model_config): every
    size an integer 1 .. its bound (_model_bound), model.grid by the grid rule (check_grid_dict)."""
    from ago_runtime.geometry.grid import check_grid_dict

    for key in _MODEL_POSITIVE + _MODEL_OPTIONAL_POSITIVE:
        v = getattr(model, key, None if key in _MODEL_OPTIONAL_POSITIVE else 1)
        if v is None and key in _MODEL_OPTIONAL_POSITIVE:
            continue
        hi = _model_bound(key)
        if not _is_int(v) or not 1 <= v <= hi:
            null = " or null" if key in _MODEL_OPTIONAL_POSITIVE else ""
            raise AgoInputError(source, f"model.{key} must be an integer 1..{hi}{null}, got {str(v)[:40]}")
    check_grid_dict(model.grid, source, "model.grid")
    for key in ("pretrained", "query_pos", "free_bias"):
        if not isinstance(getattr(model, key, True), bool):
            raise AgoInputError(source, f"model.{key} must be true or false, got {getattr(model, key)!r}")


def check_train_config(cfg, source=None):
    """`cfg` (a TrainConfig) when every value is of the right type and range; AgoInputError otherwise."""
    source = source or "training config"
    for key, lo in _INT_MIN.items():
        _int(cfg, key, lo, source)
    for key, lo in _OPTIONAL_INT_MIN.items():
        _int(cfg, key, lo, source, optional=True)
    _num(cfg, "lr", 0.0, source, strict=True)
    for key, lo in _FLOAT_MIN.items():
        _num(cfg, key, lo, source)
    _num(cfg, "warmup_max_fraction", 0.0, source, hi=1.0)
    _num(cfg, "color_jitter", 0.0, source, hi=1.0, hi_open=True)
    if cfg.min_lr > cfg.lr:
        raise AgoInputError(source, f"min_lr ({cfg.min_lr:g}) must not exceed lr ({cfg.lr:g})")
    for key in ("data", "pseudo", "prompts", "out", "train_split", "val_split", "name"):
        if not isinstance(getattr(cfg, key), str) or not getattr(cfg, key):
            raise AgoInputError(source, f"{key} must be a non-empty string, got {getattr(cfg, key)!r}")
    for key in ("gts", "init_from", "noise_bank", "text_encoder"):
        v = getattr(cfg, key)
        if v is not None and not isinstance(v, str):
            raise AgoInputError(source, f"{key} must be a string or null, got {v!r}")
    if cfg.frame_tokens is not None and (not isinstance(cfg.frame_tokens, (list, tuple))
                                         or not all(isinstance(t, str) for t in cfg.frame_tokens)):
        raise AgoInputError(source, "frame_tokens must be a list of sample tokens or null")
    from .sources import check_sources

    check_sources(cfg.sources, source)
    from .losses.sampling import SAMPLING_RULES

    if cfg.voxel_sampling not in SAMPLING_RULES:
        raise AgoInputError(source, f"voxel_sampling must be one of {list(SAMPLING_RULES)}, got {cfg.voxel_sampling!r}")
    _num(cfg, "occupied_share", 0.0, source, strict=True, hi=1.0, hi_open=True)
    from .augment import AUGMENTATIONS

    if cfg.augment not in AUGMENTATIONS:
        raise AgoInputError(source, f"augment must be one of {list(AUGMENTATIONS)}, got {cfg.augment!r}")
    from .quant import QUANT_MODES

    if cfg.quant not in QUANT_MODES:
        raise AgoInputError(source, f"quant must be one of {list(QUANT_MODES)}, got {cfg.quant!r}")
    if cfg.quant != "none" and not cfg.init_from:
        raise AgoInputError(source, f"quant={cfg.quant} fine-tunes a trained model: set init_from=CHECKPOINT "
                            "(its fp32 model is the teacher)")
    if not isinstance(cfg.feature_cache, str) or not cfg.feature_cache:
        raise AgoInputError(source, f"feature_cache must be \"off\", \"auto\" or a folder, got {cfg.feature_cache!r}")
    if cfg.snapshot_steps is not None and (not isinstance(cfg.snapshot_steps, (list, tuple))
                                           or not all(_is_int(s) and s >= 1 for s in cfg.snapshot_steps)):
        raise AgoInputError(source, f"snapshot_steps must be a list of step numbers >= 1 or null, got {cfg.snapshot_steps!r}")
    check_device(cfg.device, f"{source} (device)")
    from .amp import AMP_MODES

    if cfg.amp not in AMP_MODES:
        raise AgoInputError(source, f"amp must be one of {list(AMP_MODES)}, got {cfg.amp!r}")
    check_model_config(cfg.model, source)
    if not _is_int(cfg.model.frozen_stages) or not 0 <= cfg.model.frozen_stages <= 3:
        raise AgoInputError(source, f"model.frozen_stages must be an integer 0..3, got {cfg.model.frozen_stages!r}")
    return cfg
