"""What the experiments run: a profile (data, schedule, seeds) and the named training runs.

Every training run has a fixed name (`cw/ago`, `ow/grounding`, `fewshot/ago/seed0`, ...) and so a
fixed folder `<out>/runs/<name>`; an experiment lists the runs it needs, and a run that an earlier
experiment finished is reused (the cache), one that stopped half-way resumes.

Settings:
- `cw`: closed world; trained on pseudo-labels of the 17 Occ3D classes (prompts/cw.txt), scored on them.
- `ow`: open-world pretraining on the 5 coarse classes (prompts/ow_pretrain.txt); scored zero-shot on
  the 15 classes of prompts/ow.txt (10 known, 5 unknown).
- `fewshot`: an `ow` run fine-tuned on a k-shot subset with the 15-class pseudo-labels (one per seed).

Profiles (`ExperimentProfile.preset`):
- "cpu": what this project's 2-core CPU can run in about two hours for the whole set: a synthetic
  city of 8 scenes x 12 keyframes (6 train scenes = 72 frames, 2 val scenes = 24 frames), the `cpu`
  model preset at 100x100x8, 300 optimiser steps per run (80 per few-shot fine-tuning), k = 5 shots, two few-shot seeds.
- "tiny": the test suite's: a few steps of the tiny model on a tiny city (seconds per run).
- "full": the paper's configuration (the `full` presets, 24 epochs, k = 100, three seeds) on a
  nuScenes-layout dataset whose pseudo-labels the user made with real VLM outputs
  (`ago pseudo-labels --segmenter files --embedder files`); nothing is generated for it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from ago_runtime.errors import AgoInputError

PROFILES = ("tiny", "cpu", "full")
# loss variants of the paradigm ablation, in the paper's order
PARADIGMS = ("align", "grounding", "grounding+align", "ago")
FEWSHOT_VARIANTS = ("align", "grounding", "ago")
# diagnostic temperatures for the adapted branch's logits (Tab. 4 extra rows; chosen on val: optimistic)
ADAPTED_SCALES = (3.0, 10.0, 30.0)


@dataclass
class ExperimentProfile:
    name: str = "cpu"
    # ---- data (generated with `ago synth` / `ago pseudo-labels` unless external_data) ----
    external_data: bool = False
    data: str = "synth"                       # dataset root, relative to the experiments folder unless absolute
    synth: dict = field(default_factory=lambda: {"scenes": 8, "frames": 12, "image-size": "704x396",
                                                 "grid": "200x200x16", "seed": 0, "val-fraction": 0.25})
    pseudo_grid: str = "100x100x8"            # must be the model's grid
    sweeps: int = 10                 # keyframes superimposed per pseudo-label sample (`ago pseudo-labels --keyframes`)
    interval: int = 1
    pseudo: dict = field(default_factory=lambda: {"cw": "pseudo_cw", "ow_pretrain": "pseudo_ow_pretrain",
                                                  "ow": "pseudo_ow"})
    # ---- training ----
    train_preset: str = "cpu"                 # TrainConfig preset every run starts from
    steps: int | None = 300                   # optimiser steps per cw / ow run (None: the preset's epochs)
    fewshot_steps: int | None = 80            # optimiser steps per few-shot fine-tuning (None: fewshot_epochs)
    fewshot_epochs: int = 12
    k: int = 5                                # shots per class
    seeds: tuple[int, ...] = (0, 1)           # few-shot repeats
    train_split: str = "train"
    train_set: dict = field(default_factory=dict)  # extra TrainConfig overrides for every run
    # ---- evaluation ----
    eval_split: str = "val"
    eval_max_frames: int | None = None
    render_frames: int = 2                    # val frames drawn in the voxel-render figure

    @classmethod
    def preset(cls, name: str) -> "ExperimentProfile":
        if name == "cpu":
            return cls()
        if name == "tiny":
            return cls(name="tiny", synth={"scenes": 3, "frames": 3, "image-size": "192x128", "grid": "40x40x8",
                                           "seed": 3, "val-fraction": 0.34},
                       pseudo_grid="20x20x4", sweeps=2, train_preset="tiny", steps=2, fewshot_steps=1, k=1,
                       seeds=(0,), render_frames=1)
        if name == "full":
            return cls(name="full", external_data=True, data="data/nuscenes", synth={},
                       pseudo_grid="200x200x16", sweeps=30, interval=2,
                       pseudo={"cw": "data/nuscenes-pseudo-cw", "ow_pretrain": "data/nuscenes-pseudo-ow-pretrain",
                               "ow": "data/nuscenes-pseudo-ow"},
                       train_preset="full", steps=None, fewshot_steps=None, fewshot_epochs=12, k=100,
                       seeds=(0, 1, 2), render_frames=3)
        raise AgoInputError(None, f"unknown experiment profile {name!r}; choose one of {list(PROFILES)}")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["seeds"] = list(self.seeds)
        return d


@dataclass(frozen=True)
class RunSpec:
    """One training run: where it starts, what it learns, with which changes to the base config."""

    name: str
    setting: str                              # "cw" | "ow" | "fewshot"
    loss: tuple = ()                          # (key, value) LossConfig overrides
    model: tuple = ()                         # (key, value) ModelConfig overrides
    init_from: str | None = None              # run name whose last.pt starts this one (few-shot)
    seed: int = 0

    @property
    def prompts(self) -> str:
        return {"cw": "cw", "ow": "ow_pretrain", "fewshot": "ow"}[self.setting]


def _variant_loss(variant: str) -> tuple:
    return (("variant", variant),)


def cw_run(variant: str = "ago", **loss) -> RunSpec:
    suffix = "".join(f"-{k.replace('use_', 'no-')}" for k, v in loss.items() if v is False)
    return RunSpec(f"cw/{variant}{suffix}", "cw", _variant_loss(variant) + tuple(sorted(loss.items())))


def ow_run(variant: str = "ago", adapter_depth: int | None = None, align_loss: str | None = None) -> RunSpec:
    name, loss, model = f"ow/{variant}", _variant_loss(variant), ()
    if adapter_depth is not None and adapter_depth != 2:
        name, model = f"{name}-adapter{adapter_depth}", (("adapter_depth", adapter_depth),)
    if align_loss is not None and align_loss != "cosine":
        name, loss = f"{name}-{align_loss}", loss + (("align_loss", align_loss),)
    return RunSpec(name, "ow", loss, model)


def fewshot_run(variant: str, seed: int) -> RunSpec:
    pre = ow_run(variant)
    return RunSpec(f"fewshot/{variant}/seed{seed}", "fewshot", pre.loss, pre.model, init_from=pre.name, seed=seed)
