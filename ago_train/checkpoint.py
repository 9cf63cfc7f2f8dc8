"""Training checkpoints: one `.pt` file that `torch.load(path, weights_only=True)` can read.

A checkpoint holds ONLY tensors and plain python values (dict, list, str, int, float, bool, None):

- "format": "ago-checkpoint", "version": 1
- "model": model state_dict; "optimizer", "scheduler": their state_dicts (None in exports)
- "step", "epoch": optimiser steps done, epochs started
- "rng": {"torch": uint8 tensor, "cuda": [uint8 tensors], "numpy": {...tensor + ints}, "python": [...]}
- "model_config", "train_config", "loss_config": dicts
- "label_space": {"name", "prompt_file", "prompt_text", "class_names", "num_classes", "known"[, "class_table"]}
  (`ago_runtime.vocab.prompts.label_space_record`; "class_table" when not Occ3D-nuScenes: a shipped name or the table)
- "bank": {"encoder_id", "encoder_hash", "embeddings" (P, C) float32, "phrase_class" (P,) int64,
  "class_names", "encoder_variant"}: the label-space text embeddings, so export/eval need no text encoder
- "preprocess": Preprocess.to_dict(); "rig": the first training frame's Rig.to_dict() (native size).

Files are written through `ago_runtime.atomic.atomic_path` (temp file + rename).
"""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ago_runtime.atomic import atomic_path
from ago_runtime.errors import AgoInputError

FORMAT = "ago-checkpoint"
VERSION = 1


# ---- RNG states as tensors / lists ----------------------------------------------------------
def rng_state() -> dict:
    """torch, cuda, numpy (legacy global) and python RNG states in weights_only-loadable form."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    py = random.getstate()  # (version, tuple of 625 ints, gauss_next)
    return {
        "torch": torch.get_rng_state(),
        "cuda": [s for s in torch.cuda.get_rng_state_all()] if torch.cuda.is_available() else [],
        "numpy": {"kind": str(kind), "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)), "pos": int(pos),
                  "has_gauss": int(has_gauss), "cached": float(cached)},
        "python": [int(py[0]), [int(x) for x in py[1]], None if py[2] is None else float(py[2])],
    }


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    if state.get("cuda") and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"][: torch.cuda.device_count()])
    n = state["numpy"]
    np.random.set_state((n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached"]))
    v, keys, gauss = state["python"]
    random.setstate((v, tuple(keys), gauss))


# ---- save / load -----------------------------------------------------------------------------
def save_checkpoint(path: str | Path, payload: dict) -> Path:
    """Write `payload` (+ format/version) atomically; refuses values weights_only could not load."""
    payload = {"format": FORMAT, "version": VERSION, **payload}
    _check_plain(payload, "checkpoint")
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """Read a checkpoint with weights_only=True and check its format; AgoInputError when it is not one.

    torch's own warnings while it reads (e.g. about a plain pickle that is not a torch zip file) are
    silenced: the one error line says what is wrong with the file."""
    import warnings

    path = Path(path)
    if not path.is_file():
        raise AgoInputError(path, "checkpoint not found")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # a corrupt file, a pickle with objects, not a torch file ...
        text = str(e).strip()
        if "Weights only load failed" in text:
            raise AgoInputError(path, "not a loadable ago checkpoint: a pickle holding more than tensors and plain "
                                "values (torch.load(weights_only=True) refuses it; ago never unpickles such files)") from None
        first = (text.splitlines() or [""])[0]
        raise AgoInputError(path, f"not a loadable ago checkpoint ({e.__class__.__name__}: {first[:200]})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise AgoInputError(path, "not an ago checkpoint (no format tag)")
    if int(ckpt.get("version", -1)) > VERSION:
        raise AgoInputError(path, f"checkpoint version {ckpt.get('version')} is newer than this ago ({VERSION})")
    for key in ("model", "model_config", "label_space", "bank"):
        if key not in ckpt:
            raise AgoInputError(path, f"checkpoint lacks {key!r}")
    if not isinstance(ckpt["model"], dict):
        raise AgoInputError(path, "checkpoint 'model' is not a state dict of tensors")
    for name, t in ckpt["model"].items():   # NaN / inf weights predict nothing: refused before any work
        if isinstance(t, torch.Tensor) and t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise AgoInputError(path, f"weight {name!r} holds NaN or inf")
    check_checkpoint_config(ckpt, path)
    return ckpt


def check_checkpoint_config(ckpt: dict, path) -> None:
    """A checkpoint's model_config and rig record by value, before any model is built from them: the config's
    keys, sizes in range and grid (ModelConfig.from_dict), the rig's calibration (Rig.validate) and camera count;
    AgoInputError(path, "model_config: ..." / "rig: ...")."""
    from ago_runtime.geometry.camera import Rig

    from .model import ModelConfig

    config = ckpt["model_config"]
    if not isinstance(config, dict):
        raise AgoInputError(path, f"model_config: not a record of model settings ({type(config).__name__})")
    try:
        cfg = ModelConfig.from_dict(plain_dict(dict(config)), source="model_config")
    except AgoInputError as e:
        raise AgoInputError(path, f"model_config: {e.problem}") from None
    except (TypeError, ValueError, AttributeError, KeyError) as e:
        raise AgoInputError(path, f"model_config: malformed ({e.__class__.__name__}: {str(e)[:160]})") from None
    if "rig" not in ckpt:
        return
    try:
        rig = Rig.from_dict(plain_dict(ckpt["rig"]))
    except (TypeError, ValueError, AttributeError, KeyError, IndexError) as e:
        raise AgoInputError(path, f"rig: malformed ({e.__class__.__name__}: {str(e)[:160]})") from None
    try:
        rig.validate("rig")
    except AgoInputError as e:
        raise AgoInputError(path, f"rig: {e.problem}") from None
    if len(rig.cameras) != cfg.num_cameras:
        raise AgoInputError(path, f"rig: {len(rig.cameras)} cameras, model_config.num_cameras says {cfg.num_cameras}")


_PLAIN = (str, int, float, bool, type(None))


def _check_plain(obj: Any, where: str) -> None:
    """Raise TypeError on anything but tensors and plain python containers/scalars."""
    if isinstance(obj, (torch.Tensor,) + _PLAIN):
        return
    if isinstance(obj, dict):
        for k, v in obj.items():
            if not isinstance(k, (str, int)):
                raise TypeError(f"{where}: key {k!r} is not str/int")
            _check_plain(v, f"{where}.{k}")
        return
    if isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            _check_plain(v, f"{where}[{i}]")
        return
    raise TypeError(f"{where}: {type(obj).__name__} cannot go into a weights_only checkpoint")


def plain(obj: Any) -> Any:
    """numpy scalars/arrays and tuples -> python values / tensors / lists (for config dicts)."""
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(obj.copy())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


# ---- checks of what a checkpoint is used for ------------------------------------------------
def config_differences(saved: dict, current: dict, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two (nested) config dicts, e.g. ["embed_dim", "grid.shape"]."""
    out = []
    for key in sorted(set(saved) | set(current)):
        a, b = saved.get(key), current.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += config_differences(a, b, f"{prefix}{key}.")
        elif (list(a) if isinstance(a, tuple) else a) != (list(b) if isinstance(b, tuple) else b):
            out.append(f"{prefix}{key}")
    return out


def load_model_weights(model: torch.nn.Module, ckpt: dict, path: str | Path, model_config: dict | None = None,
                       what: str = "the model") -> None:
    """model.load_state_dict(ckpt["model"], strict) or one AgoInputError naming the checkpoint.

    When `model_config` (the config `model` was built from) is given and differs from the checkpoint's
    own model_config, the message lists the keys that differ (e.g. a changed model size)."""
    state = ckpt.get("model")
    if not isinstance(state, dict):
        raise AgoInputError(path, "checkpoint has no model weights")
    diff = []
    if model_config is not None and isinstance(ckpt.get("model_config"), dict):
        diff = [k for k in config_differences(plain_dict(ckpt["model_config"]), plain_dict(model_config))
                if k not in ("pretrained",)]
    try:
        model.load_state_dict(state, strict=True)
    except (RuntimeError, KeyError, ValueError, TypeError) as e:
        detail = f"; model settings that differ: {', '.join(diff[:8])}" if diff else ""
        raise AgoInputError(path, f"its weights do not fit {what} ({state_dict_problem(e)}){detail}") from None


def state_dict_problem(e: BaseException) -> str:
    """The telling line of torch's load_state_dict error ("size mismatch for decoder.0.weight: ... [32, 64]
    ... [24, 64]", "Missing key(s) ..."), shortened, instead of its generic first line."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    for ln in lines:
        if ln.startswith(("size mismatch", "Missing key", "Unexpected key")):
            ln = ln.replace("copying a param with shape ", "").replace("torch.Size", "")
            return ln[:200]
    return (lines[0] if lines else e.__class__.__name__)[:200]


def plain_dict(d: Any) -> Any:
    """Tensors in a config dict -> lists (to compare configs saved in checkpoints with fresh ones)."""
    if isinstance(d, dict):
        return {k: plain_dict(v) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [plain_dict(v) for v in d]
    if isinstance(d, torch.Tensor):
        return d.tolist()
    return d


def check_resume_model(ckpt: dict, path: str | Path, model_config: dict) -> None:
    """Refuse to resume from a checkpoint whose model settings differ from this run's (a changed model
    size would otherwise fail deep inside load_state_dict, or silently if shapes happened to agree)."""
    saved = ckpt.get("model_config")
    if not isinstance(saved, dict):
        raise AgoInputError(path, "checkpoint has no model_config; cannot resume from it")
    diff = [k for k in config_differences(plain_dict(saved), plain_dict(model_config)) if k not in ("pretrained",)]
    if diff:
        raise AgoInputError(path, "cannot resume: model settings differ from this run's "
                                  f"({', '.join(diff[:8])}); use the run's own config or another --out")


def check_checkpoint_bank(ckpt: dict, path: str | Path, bank: dict) -> None:
    """Refuse a checkpoint (to resume from, or to start from) whose prompt bank came from another text encoder than
    this run's bank (`bank`: the 'bank' dict), one line naming both encoders."""
    from ago_runtime.vocab.model_folder import check_same_encoder

    saved = ckpt.get("bank") if isinstance(ckpt.get("bank"), dict) else {}
    if "encoder_id" in saved:
        check_same_encoder("the checkpoint's prompt bank", str(saved["encoder_id"]), "this run's prompt bank",
                           str(bank["encoder_id"]), source=path)


def checkpoint_camera_names(ckpt: dict, path: str | Path | None = None) -> list[str] | None:
    """The cameras the checkpoint's model takes, in its input order (its training rig), or None for a checkpoint
    without a rig record (it then takes each frame's cameras as they come, as before rigs were recorded)."""
    rig = ckpt.get("rig")
    if not isinstance(rig, dict) or not isinstance(rig.get("cameras"), list):
        return None
    names = [c.get("name") for c in rig["cameras"] if isinstance(c, dict)]
    if len(names) != len(rig["cameras"]) or not all(isinstance(n, str) for n in names):
        raise AgoInputError(path, "checkpoint rig record: every camera needs a name")
    return names
