"""Training checkpoints: `CheckpointContract`, the one writer and the one reader of an ago `.pt` checkpoint.

A checkpoint is one file `torch.load(path, weights_only=True)` can read: ONLY tensors and plain python values
(dict, list, str, int, float, bool, None). `CheckpointContract.save` (`to_payload`) is the only code that builds
its dict and `CheckpointContract.load` (`from_payload`) the only code that reads one; the trainer, its
snapshots, `ago calibrate` and `ago_export.testing.random_checkpoint` all write a contract, and export, eval,
resume, init_from, the experiments and the benchmarks read its attributes. Layout, version 1 (PAYLOAD_KEYS;
optional keys are left out when they hold nothing, and read as None):

- "format": "ago-checkpoint", "version": 1 (derived)
- "model": the model's state_dict; "model_config": ModelConfig.to_dict() (`CheckpointContract.model_config`)
- "optimizer", "scheduler": state dicts, "rng": `rng_state()` (a list of them, one per rank, from DDP):
  `TrainingState`, all three or none (a model-only snapshot or `random_checkpoint` has none)
- "step", "epoch": optimiser steps done, epochs started; "total_steps", "world_size": the run's length, processes
- "train_config": the run's TrainConfig.to_dict() as recorded; "loss_config": its "loss" (derived, checked)
- "label_space": {"name", "prompt_file", "prompt_text", "class_names", "num_classes", "known"[, "class_table"]}
  (`LabelSpaceRecord`; "class_table" when not Occ3D-nuScenes: a shipped name or the table)
- "bank": {"encoder_id", "encoder_hash", "encoder_variant", "embeddings" (P, C) float32, "phrase_class" (P,)
  int64, "class_names"} (`BankRecord`): the label-space text embeddings, so export/eval need no text encoder
- "preprocess": Preprocess(model_config.image_width, image_height).to_dict() (derived, checked)
- "rig": the first training frame's Rig.to_dict() (native size); "align_center": (C,) float32 or absent
- "calibration": `CalibrationRecord` (calibrate.py: scales, adapted-branch statistics) or absent

The reader refuses, with one AgoInputError line naming the file: another format tag, a version it does not
read (a newer one: "upgrade ago"), a key outside the layout, and any value out of type, shape or range.
"""

from __future__ import annotations

import dataclasses

import math
import random
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ago_runtime.atomic import atomic_path
from ago_runtime.classes import table_from_ref, table_record
from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.camera import Rig
from ago_runtime.geometry.preprocess import Preprocess
from ago_runtime.vocab.bank import PromptBank
from ago_runtime.vocab.prompts import LabelSpace, parse_prompt_text

from .model.config import ModelConfig

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


# ---- comparing configs, naming a state-dict mismatch ------------------------------------------
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


# ---- the contract ------------------------------------------------------------------------------
PAYLOAD_KEYS = ("format", "version", "model", "optimizer", "scheduler", "step", "epoch", "total_steps", "world_size",
                "rng", "model_config", "train_config", "loss_config", "label_space", "bank", "preprocess", "rig",
                "align_center", "calibration")
REQUIRED_KEYS = ("format", "version", "model", "model_config", "label_space", "bank")
# keys the writer derives from other fields and the reader checks against them (never stored twice in a contract)
DERIVED_KEYS = {"format": "the format tag", "version": "VERSION", "loss_config": "train_config['loss']",
                "preprocess": "Preprocess(model_config.image_width, image_height).to_dict()"}
MAX_STATE_TENSORS = 100_000     # weights in a state dict (the full model has ~600)
MAX_NAME_CHARS = 500            # an encoder id / hash / variant, a class name


def _need(ok: bool, source, problem: str) -> None:
    if not ok:
        raise AgoInputError(source, problem)


def _int_at_least(d: dict, key: str, lo: int, source, default=None):
    v = d.get(key, default)
    if v is None:
        return None
    _need(isinstance(v, int) and not isinstance(v, bool) and v >= lo, source, f"{key}: must be an integer >= {lo}, got {v!r}")
    return int(v)


def _str_list(v, source, what: str) -> list[str]:
    _need(isinstance(v, list) and all(isinstance(x, str) and len(x) <= MAX_NAME_CHARS for x in v), source,
          f"{what}: must be a list of names")
    return list(v)


def _tensor(v, source, what: str, dtype: torch.dtype, shape: tuple) -> torch.Tensor:
    """`v` when it is a tensor of `dtype` and `shape` (None entries: any size), finite when floating."""
    _need(isinstance(v, torch.Tensor), source, f"{what}: not a tensor")
    _need(v.dtype == dtype and v.ndim == len(shape) and all(s is None or s == n for s, n in zip(shape, v.shape)),
          source, f"{what}: {str(v.dtype).replace('torch.', '')} {tuple(v.shape)}, expected "
                  f"{str(dtype).replace('torch.', '')} ({', '.join('N' if s is None else str(s) for s in shape)})")
    _need(not v.is_floating_point() or bool(torch.isfinite(v).all()), source, f"{what}: holds NaN or inf")
    return v


@dataclass
class LabelSpaceRecord:
    """The label space a checkpoint was trained on, rebuilt without the prompt file or its table file: the prompt
    text, its classes and, when not Occ3D-nuScenes, its class table (a shipped name or the table's JSON form:
    `ago_runtime.classes.table_record`). `space` is the LabelSpace parsed from the text (checked to agree)."""
    name: str | None
    prompt_file: str | None
    prompt_text: str
    class_names: list[str]
    num_classes: int
    known: list[str]
    class_table: str | dict | None = None
    space: LabelSpace | None = field(default=None, init=False, repr=False, compare=False)

    @classmethod
    def of_space(cls, space: LabelSpace, prompt_text: str) -> "LabelSpaceRecord":
        ref = table_record(space.class_table).get("class_table")
        rec = cls(space.name, str(space.source) if space.source is not None else None, prompt_text,
                  list(space.class_names), int(space.num_classes), sorted(space.known), ref)
        rec.space = space
        return rec

    def to_payload(self) -> dict:
        d = {"name": self.name, "prompt_file": self.prompt_file, "prompt_text": self.prompt_text,
             "class_names": list(self.class_names), "num_classes": int(self.num_classes), "known": list(self.known)}
        return d if self.class_table is None else {**d, "class_table": self.class_table}

    @classmethod
    def from_payload(cls, d, source) -> "LabelSpaceRecord":
        _need(isinstance(d, dict), source, "label_space: not a record")
        unknown = sorted(set(d) - {"name", "prompt_file", "prompt_text", "class_names", "num_classes", "known",
                                   "class_table"})
        _need(not unknown, source, f"label_space: unknown fields {unknown}")
        _need(isinstance(d.get("prompt_text"), str), source, "label_space: no prompt_text")
        for key in ("name", "prompt_file"):
            _need(d.get(key) is None or isinstance(d[key], str), source, f"label_space.{key}: not a string")
        table = table_from_ref(d["class_table"], f"{source} (label_space.class_table)") if "class_table" in d else None
        space = parse_prompt_text(d["prompt_text"], name=d.get("name"), source=f"{source} (label_space)", table=table)
        names = _str_list(d.get("class_names", list(space.class_names)), source, "label_space.class_names")
        _need(names == list(space.class_names), source, "label_space: class names disagree with its prompt text")
        num = _int_at_least(d, "num_classes", 1, source, default=len(names))
        _need(num == len(names), source, f"label_space: num_classes {num} but {len(names)} class names")
        known = _str_list(d.get("known", sorted(space.known)), source, "label_space.known")
        _need(sorted(known) == sorted(space.known), source, "label_space: known classes disagree with its prompt text")
        rec = cls(d.get("name"), d.get("prompt_file"), d["prompt_text"], names, num, known, d.get("class_table"))
        rec.space = space
        return rec


@dataclass
class BankRecord:
    """The label space's text embeddings the model was trained with, so export and eval need no text encoder:
    (P, C) float32 `embeddings`, (P,) int64 `phrase_class` (the label space's phrases, in its order)."""
    encoder_id: str
    encoder_hash: str
    embeddings: torch.Tensor
    phrase_class: torch.Tensor
    class_names: list[str]
    encoder_variant: str = ""

    @property
    def dim(self) -> int:
        return int(self.embeddings.shape[1])

    @classmethod
    def of_bank(cls, bank: PromptBank) -> "BankRecord":
        return cls(str(bank.encoder_id), str(bank.encoder_hash),
                   torch.as_tensor(np.asarray(bank.embeddings, dtype=np.float32)),
                   torch.as_tensor(np.asarray(bank.phrase_class, dtype=np.int64)),
                   [str(c) for c in bank.class_names], str(bank.encoder_variant or ""))

    def to_payload(self) -> dict:
        return {"encoder_id": self.encoder_id, "encoder_hash": self.encoder_hash, "encoder_variant": self.encoder_variant,
                "embeddings": self.embeddings, "phrase_class": self.phrase_class, "class_names": list(self.class_names)}

    @classmethod
    def from_payload(cls, d, source, space: LabelSpace, embed_dim: int) -> "BankRecord":
        _need(isinstance(d, dict), source, "bank: not a record")
        unknown = sorted(set(d) - {"encoder_id", "encoder_hash", "encoder_variant", "embeddings", "phrase_class",
                                   "class_names"})
        _need(not unknown, source, f"bank: unknown fields {unknown}")
        for key in ("encoder_id", "encoder_hash", "encoder_variant"):
            v = d.get(key, "")
            _need(isinstance(v, str) and len(v) <= MAX_NAME_CHARS and (v or key == "encoder_variant"), source,
                  f"bank.{key}: not a name")
        p = len(space.phrases)
        emb = _tensor(d.get("embeddings"), source, "bank.embeddings", torch.float32, (p, embed_dim))
        pc = _tensor(d.get("phrase_class"), source, "bank.phrase_class", torch.int64, (p,))
        _need(np.array_equal(pc.numpy(), space.phrase_class), source,
              "bank.phrase_class: not the phrase classes of its label space")
        names = _str_list(d.get("class_names"), source, "bank.class_names")
        _need(names == list(space.class_names), source, "bank.class_names: not its label space's classes")
        return cls(d["encoder_id"], d["encoder_hash"], emb, pc, names, d.get("encoder_variant", ""))

    def prompt_bank(self, space: LabelSpace) -> PromptBank:
        """The bank as the runtime's PromptBank of `space` (the checkpoint's own label space)."""
        emb = self.embeddings.detach().cpu().numpy().astype(np.float32)
        return PromptBank(
            embeddings=emb, phrases=space.phrases, class_names=list(space.class_names),
            phrase_class=self.phrase_class.detach().cpu().numpy().astype(np.int64), encoder_id=self.encoder_id,
            encoder_variant=self.encoder_variant or "checkpoint", encoder_hash=self.encoder_hash, dim=self.dim,
            source_hash=space.sha256, label_space=space.name, known=[c for c in space.class_names if c in space.known],
            occ3d_ids=[c.occ3d_ids for c in space.classes], class_table=space.class_table)


@dataclass
class TrainingState:
    """What only resuming needs: the optimiser's and scheduler's state dicts and the RNG states (`rng_state()`, or
    one per rank of a DDP run). A model-only snapshot has none (`CheckpointContract.training` None)."""
    optimizer: dict
    scheduler: dict
    rng: dict | list

    @classmethod
    def from_payload(cls, d: dict, source) -> "TrainingState | None":
        parts = {k: d.get(k) for k in ("optimizer", "scheduler", "rng")}
        if all(v is None for v in parts.values()):
            return None
        missing = [k for k, v in parts.items() if v is None]
        _need(not missing, source, f"training state incomplete: no {', '.join(missing)} (a checkpoint has all of "
                                   "optimizer, scheduler, rng or none)")
        opt = parts["optimizer"]
        _need(isinstance(opt, dict) and isinstance(opt.get("state"), dict) and isinstance(opt.get("param_groups"), list),
              source, "optimizer: not an optimiser state dict")
        _need(isinstance(parts["scheduler"], dict), source, "scheduler: not a scheduler state dict")
        rng = parts["rng"]
        for r in rng if isinstance(rng, list) else [rng]:
            _need(isinstance(r, dict) and isinstance(r.get("torch"), torch.Tensor) and isinstance(r.get("numpy"), dict)
                  and isinstance(r.get("python"), list), source, "rng: not the RNG states rng_state() records")
        return cls(opt, parts["scheduler"], rng)

    def rng_of_rank(self, rank: int) -> dict:
        return self.rng[rank] if isinstance(self.rng, list) else self.rng


CALIBRATION_FLOATS = ("scale_main", "scale_adapted", "nll_main", "nll_adapted", "entropy_main", "scale_adapted_nll",
                      "scale_adapted_entropy")


@dataclass
class CalibrationRecord:
    """The open-world identifier's calibration (ago_train/calibrate.py `fit_scales`): the two branches' logit
    scales and, when the run had aligned voxels, the adapted branch's (C,) mean and (C, C) covariance. Fields
    other than the scales are None when fit_scales did not record them (an empty fit, an older run)."""
    scale_main: float = 1.0
    scale_adapted: float = 1.0
    voxels: int = 0
    frames: int = 0
    nll_main: float | None = None
    nll_adapted: float | None = None
    entropy_main: float | None = None
    scale_adapted_nll: float | None = None
    scale_adapted_entropy: float | None = None
    adapted_rule: str | None = None
    adapted_mean: torch.Tensor | None = None
    adapted_cov: torch.Tensor | None = None
    adapted_voxels: int | None = None

    def to_payload(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}

    @classmethod
    def from_payload(cls, d, source, embed_dim: int) -> "CalibrationRecord":
        _need(isinstance(d, dict), source, "calibration: not a record")
        unknown = sorted(set(d) - {f.name for f in fields(cls)})
        _need(not unknown, source, f"calibration: unknown fields {unknown}")
        kw: dict = {}
        for key in CALIBRATION_FLOATS:
            v = d.get(key)
            _need(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)), source,
                  f"calibration.{key}: not a number")
            if v is not None:
                kw[key] = float(v)
        for key in ("scale_main", "scale_adapted"):
            _need(key in kw and math.isfinite(kw[key]) and kw[key] > 0, source,
                  f"calibration.{key}: must be a finite number > 0")
        for key in ("voxels", "frames", "adapted_voxels"):
            if key in d:
                kw[key] = _int_at_least(d, key, 0, f"{source}", None)
        if d.get("adapted_rule") is not None:
            _need(d["adapted_rule"] in ("nll", "entropy"), source, "calibration.adapted_rule: 'nll' or 'entropy'")
            kw["adapted_rule"] = d["adapted_rule"]
        _need(("adapted_mean" in d) == ("adapted_cov" in d), source, "calibration: adapted_mean without adapted_cov")
        if "adapted_mean" in d:
            kw["adapted_mean"] = _tensor(d["adapted_mean"], source, "calibration.adapted_mean", torch.float32, (embed_dim,))
            kw["adapted_cov"] = _tensor(d["adapted_cov"], source, "calibration.adapted_cov", torch.float32,
                                        (embed_dim, embed_dim))
        return cls(**kw)

    @property
    def scales(self) -> tuple[float, float]:
        return float(self.scale_main), float(self.scale_adapted)

    def adapted_stats(self) -> dict | None:
        """{"adapted_mean", "adapted_cov"} (model/scoring.py `adapted_logits`), or None without statistics."""
        if self.adapted_mean is None:
            return None
        return {"adapted_mean": self.adapted_mean, "adapted_cov": self.adapted_cov}


@dataclass
class CheckpointContract:
    """One ago checkpoint, typed (the module docstring gives the file layout). `to_payload` is the only writer
    (`save`), `from_payload` / `load` the only reader; consumers read attributes, never the file's keys."""
    model: dict                       # the model's state dict (tensors)
    model_config: ModelConfig
    label_space: LabelSpaceRecord
    bank: BankRecord
    step: int = 0                     # optimiser steps done
    epoch: int = 0                    # epochs started
    training: TrainingState | None = None   # optimizer, scheduler, rng: None in a model-only snapshot
    total_steps: int | None = None    # the run's planned length (the trainer's)
    world_size: int | None = None     # processes of the run (resume needs the same)
    train_config: dict | None = None  # the run's TrainConfig.to_dict() as recorded (settings for the record: the
    # card, resume checks; kept a record, not a TrainConfig, so a checkpoint outlives renamed settings)
    rig: Rig | None = None            # the training rig (native size): the cameras the model takes, in order
    align_center: torch.Tensor | None = None   # (C,) mean E_3D the alignment loss subtracted (LossConfig.align_center)
    calibration: CalibrationRecord | None = None

    # ---- derived values -------------------------------------------------------------------------
    @property
    def preprocess(self) -> Preprocess:
        return Preprocess(self.model_config.image_width, self.model_config.image_height)

    @property
    def loss_config(self) -> dict | None:
        return None if self.train_config is None else self.train_config.get("loss")

    @property
    def text_encoder(self) -> str | None:
        """The CLIP folder the run's bank came from (train_config text_encoder), or None (the torch MiniLM)."""
        v = (self.train_config or {}).get("text_encoder")
        return v if isinstance(v, str) else None

    @property
    def space(self) -> LabelSpace:
        """The training label space (parsed from the recorded prompt text)."""
        return self.label_space.space

    @property
    def camera_names(self) -> list[str] | None:
        """The cameras the model takes, in its input order (its training rig), or None without a rig record (it
        then takes each frame's cameras as they come, as before rigs were recorded)."""
        return None if self.rig is None else list(self.rig.names)

    @property
    def scales(self) -> tuple[float, float]:
        """(scale_main, scale_adapted) of the identifier: the calibration's, else (1, 1)."""
        return (1.0, 1.0) if self.calibration is None else self.calibration.scales

    @property
    def adapted_stats(self) -> dict | None:
        return None if self.calibration is None else self.calibration.adapted_stats()

    # ---- writer -----------------------------------------------------------------------------------
    def to_payload(self) -> dict:
        """The plain dict `torch.save` writes: every field under its key (PAYLOAD_KEYS), the derived keys
        (DERIVED_KEYS) computed here; optional fields that are None are left out (absent = none)."""
        t = self.training
        payload = {
            "format": FORMAT, "version": VERSION, "model": self.model,
            "optimizer": None if t is None else t.optimizer, "scheduler": None if t is None else plain(t.scheduler),
            "step": int(self.step), "epoch": int(self.epoch), "total_steps": self.total_steps,
            "world_size": self.world_size, "rng": None if t is None else t.rng,
            "model_config": plain(self.model_config.to_dict()),
            "train_config": None if self.train_config is None else plain(self.train_config),
            "loss_config": None if self.loss_config is None else plain(self.loss_config),
            "label_space": self.label_space.to_payload(), "bank": self.bank.to_payload(),
            "preprocess": plain(self.preprocess.to_dict()),
            "rig": None if self.rig is None else plain(self.rig.to_dict()),
            "align_center": self.align_center,
            "calibration": None if self.calibration is None else self.calibration.to_payload(),
        }
        return {k: v for k, v in payload.items() if v is not None}

    def model_only(self) -> "CheckpointContract":
        """This checkpoint without its training state (optimiser, scheduler, RNG): what a snapshot holds, and what
        is kept of a finished run to export it again (models/default/checkpoint.pt)."""
        return dataclasses.replace(self, training=None)

    def save(self, path: str | Path) -> Path:
        """Write atomically (temp file + rename); refuses values weights_only could not load (TypeError)."""
        payload = self.to_payload()
        _check_plain(payload, "checkpoint")
        path = Path(path)
        with atomic_path(path) as tmp:
            torch.save(payload, tmp)
        return path

    # ---- reader -----------------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path, map_location: str | torch.device = "cpu") -> "CheckpointContract":
        """Read a checkpoint with weights_only=True and check it by value (`from_payload`); AgoInputError naming
        `path` when it is not one. torch's own warnings while it reads are silenced: the one error line says what
        is wrong with the file."""
        import warnings

        path = Path(path)
        if not path.is_file():
            raise AgoInputError(path, "checkpoint not found")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                payload = torch.load(path, map_location=map_location, weights_only=True)
        except Exception as e:  # a corrupt file, a pickle with objects, not a torch file ...
            text = str(e).strip()
            if "Weights only load failed" in text:
                raise AgoInputError(path, "not a loadable ago checkpoint: a pickle holding more than tensors and plain "
                                    "values (torch.load(weights_only=True) refuses it; ago never unpickles such files)") from None
            first = (text.splitlines() or [""])[0]
            raise AgoInputError(path, f"not a loadable ago checkpoint ({e.__class__.__name__}: {first[:200]})") from None
        return cls.from_payload(payload, path)

    @classmethod
    def from_payload(cls, payload, source) -> "CheckpointContract":
        """The contract of a loaded payload, checked by value before any model is built from it: the format tag and
        version, no key outside PAYLOAD_KEYS, the model_config (ModelConfig.from_dict: keys, sizes, grid), finite
        weights, the rig (Rig.validate, camera count), the label space against its prompt text, the bank's arrays
        against the label space and embed_dim, the calibration's, and the derived keys against what they derive
        from. AgoInputError(source, ...) otherwise."""
        _need(isinstance(payload, dict) and payload.get("format") == FORMAT, source,
              f"not an ago checkpoint (no {FORMAT!r} format tag)")
        version = payload.get("version")
        if isinstance(version, int) and not isinstance(version, bool) and version > VERSION:
            raise AgoInputError(source, f"checkpoint version {version} is newer than this ago reads (version {VERSION}): "
                                "upgrade ago")
        _need(version == VERSION and not isinstance(version, bool), source,
              f"checkpoint version {version!r} is not one this ago reads (version {VERSION}): train it again with "
              "this ago, or export it with the ago that wrote it")
        unknown = sorted(str(k) for k in payload if k not in PAYLOAD_KEYS)
        _need(not unknown, source, f"checkpoint fields {unknown} are not in the version-{VERSION} layout (written by "
                                   "another tool or a newer ago: upgrade ago)")
        for key in REQUIRED_KEYS:
            _need(key in payload, source, f"checkpoint lacks {key!r}")
        state = payload["model"]
        _need(isinstance(state, dict) and len(state) <= MAX_STATE_TENSORS
              and all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()), source,
              "checkpoint 'model' is not a state dict of tensors")
        for name, t in state.items():   # NaN / inf weights predict nothing: refused before any work
            _need(not t.is_floating_point() or bool(torch.isfinite(t).all()), source, f"weight {name!r} holds NaN or inf")
        cfg = _model_config(payload["model_config"], source)
        rig = _rig(payload.get("rig"), cfg, source)
        label_space = LabelSpaceRecord.from_payload(payload["label_space"], source)
        bank = BankRecord.from_payload(payload["bank"], source, label_space.space, cfg.embed_dim)
        train_config = payload.get("train_config")
        _need(train_config is None or (isinstance(train_config, dict) and all(isinstance(k, str) for k in train_config)),
              source, "train_config: not a record of training settings")
        align = payload.get("align_center")
        if align is not None:
            _tensor(align, source, "align_center", torch.float32, (cfg.embed_dim,))
        cal = payload.get("calibration")
        contract = cls(
            model=state, model_config=cfg, label_space=label_space, bank=bank,
            step=_int_at_least(payload, "step", 0, source, 0), epoch=_int_at_least(payload, "epoch", 0, source, 0),
            training=TrainingState.from_payload(payload, source),
            total_steps=_int_at_least(payload, "total_steps", 0, source), world_size=_int_at_least(payload, "world_size", 1, source),
            train_config=train_config, rig=rig, align_center=align,
            calibration=None if cal is None else CalibrationRecord.from_payload(cal, source, cfg.embed_dim))
        contract.check_derived(payload, source)
        return contract

    def check_derived(self, payload: dict, source) -> None:
        """The derived keys a payload holds (DERIVED_KEYS) agree with the fields they derive from, and train_config's
        model copy with model_config."""
        derived = self.to_payload()
        for key in ("loss_config", "preprocess"):
            if key in payload:
                _need(plain_dict(payload[key]) == plain_dict(derived.get(key)), source,
                      f"{key} differs from {DERIVED_KEYS[key]} (a copy of it)")
        if self.train_config is not None and "model" in self.train_config:
            _need(plain_dict(self.train_config["model"]) == plain_dict(derived["model_config"]), source,
                  "train_config.model differs from model_config (a copy of it)")

    # ---- what a checkpoint is used for -----------------------------------------------------------
    def load_weights(self, model: torch.nn.Module, source, model_config: ModelConfig | None = None,
                     what: str = "the model") -> None:
        """model.load_state_dict(self.model, strict) or one AgoInputError naming `source`. When `model_config` (the
        config `model` was built from) differs from the checkpoint's, the message lists the keys that differ."""
        diff = [] if model_config is None else self.config_differences(model_config)
        try:
            model.load_state_dict(self.model, strict=True)
        except (RuntimeError, KeyError, ValueError, TypeError) as e:
            detail = f"; model settings that differ: {', '.join(diff[:8])}" if diff else ""
            raise AgoInputError(source, f"its weights do not fit {what} ({state_dict_problem(e)}){detail}") from None

    def build_model(self, source) -> torch.nn.Module:
        """The checkpoint's model with its weights, in eval mode (no backbone_weights file read)."""
        model = self.model_config.build(load_weights=False)
        self.load_weights(model, source, what="its own model_config")
        return model.eval()

    def config_differences(self, model_config: ModelConfig) -> list[str]:
        return [k for k in config_differences(plain_dict(self.model_config.to_dict()), plain_dict(model_config.to_dict()))
                if k != "pretrained"]

    def check_same_encoder(self, source, bank: BankRecord) -> None:
        """Refuse a checkpoint (to resume from, or to start from) whose bank came from another text encoder than
        this run's `bank`, one line naming both encoders."""
        from ago_runtime.vocab.model_folder import check_same_encoder

        check_same_encoder("the checkpoint's prompt bank", self.bank.encoder_id, "this run's prompt bank",
                           bank.encoder_id, source=source)

    def check_resume(self, source, train_config, world_size: int, bank: BankRecord) -> None:
        """Refuse to resume this checkpoint into a run of `train_config` (a TrainConfig) on `world_size` processes
        with `bank`: no training state (an export or a snapshot), a bank of another text encoder (first: it also
        changes embed_dim), other model settings, another schedule, seed or process count."""
        _need(self.training is not None, source, "checkpoint has no optimiser state (an export?); cannot resume from it")
        self.check_same_encoder(source, bank)
        diff = self.config_differences(train_config.model)
        _need(not diff, source, f"cannot resume: model settings differ from this run's ({', '.join(diff[:8])}); use "
                                "the run's own config or another --out")
        saved = self.train_config or {}
        for key in ("epochs", "batch_size", "seed", "max_steps"):
            _need(saved.get(key) == getattr(train_config, key), source,
                  f"cannot resume: {key} was {saved.get(key)!r}, now {getattr(train_config, key)!r}")
        _need((self.world_size or 1) == world_size, source,
              f"cannot resume: the run used {self.world_size} processes, now {world_size}")


def _model_config(config, source) -> ModelConfig:
    """The checkpoint's model_config by value (keys, sizes in range, grid: ModelConfig.from_dict)."""
    _need(isinstance(config, dict), source, f"model_config: not a record of model settings ({type(config).__name__})")
    try:
        return ModelConfig.from_dict(plain_dict(dict(config)), source="model_config")
    except AgoInputError as e:
        raise AgoInputError(source, f"model_config: {e.problem}") from None
    except (TypeError, ValueError, AttributeError, KeyError) as e:
        raise AgoInputError(source, f"model_config: malformed ({e.__class__.__name__}: {str(e)[:160]})") from None


def _rig(record, cfg: ModelConfig, source) -> Rig | None:
    """The recorded training rig by value (Rig.validate, camera names, camera count), or None without one."""
    if record is None:
        return None
    try:
        rig = Rig.from_dict(plain_dict(record))
    except (TypeError, ValueError, AttributeError, KeyError, IndexError) as e:
        raise AgoInputError(source, f"rig: malformed ({e.__class__.__name__}: {str(e)[:160]})") from None
    try:
        rig.validate("rig")
    except AgoInputError as e:
        raise AgoInputError(source, f"rig: {e.problem}") from None
    _need(all(isinstance(c.name, str) and c.name for c in rig.cameras), source, "rig: every camera needs a name")
    _need(len(rig.cameras) == cfg.num_cameras, source,
          f"rig: {len(rig.cameras)} cameras, model_config.num_cameras says {cfg.num_cameras}")
    return rig
