"""What the experiments run: a profile (data, schedule, seeds) and the named training runs.

Every training run has a fixed name (`cw/ago`, `ow/grounding`, `fewshot/ago/seed0`, ...) and so a
fixed folder `<out>/runs/<name>`; an experiment lists the runs it needs, and a run that an earlier
experiment finished is reused (the cache), one that stopped half-way resumes.

Settings:
- `cw`: closed world; trained on pseudo-labels of the 17 Occ3D classes (prompts/cw.txt), scored on them.
- `ow`: open-world pretraining on the 5 coarse classes (prompts/ow_pretrain.txt); scored zero-shot on
  the 15 classes of prompts/ow.txt (10 known, 5 unknown).
- `fewshot`: an `ow` run fine-tuned on a k-shot subset with the 15-class pseudo-labels (one per seed).

Datasets (`RunSpec.dataset`): "nuscenes" (the runs above, on the profile's nuScenes-layout city) and
"waymo" (Tab. G and H of the paper: `waymo/cw/ago`, `waymo/ow/ago`, `waymo/fewshot/ago/seed<s>` on a
synthetic Occ3D-Waymo city, `ago synth --rig waymo`, in its own folders: `ExperimentProfile.waymo`). The
label spaces of each dataset are PROMPTS[dataset]: for Waymo the shipped prompts/waymo/*.txt.

Profiles (`ExperimentProfile.preset`):
- "cpu": what this project's 2-core CPU can run in a few hours for the whole set (38 nuScenes runs + 6 Waymo
  runs): a
  synthetic city of 12 scenes x 12 keyframes (9 train scenes = 108 frames, 3 val scenes = 36 frames),
  the `cpu` recipe (the default bundle's: stratified voxel sample, cached frozen stages) at 100x100x8,
  1000 optimiser steps per run (150 per few-shot fine-tuning), k = 5 shots, two seeds, and the
  open-world recipe (`ow_loss`: docs/training.md, "Matter of no training class") on every open-world
  and few-shot run. The Waymo city has the nuScenes city's scenes, frames, grid and seed, with 3:2 images
  (576x384: Waymo's front cameras are 1920x1280), and its runs the model canvas 288x192 (3:2, the
  nuScenes canvas' height; `WaymoSetting.model`).
- "tiny": the test suite's: a few steps of the tiny model on a tiny city (seconds per run).
- "full": the paper's configuration (the `full` presets, 24 epochs, k = 100, three seeds, the paper's
  losses: no open-world terms) on a nuScenes-layout dataset whose pseudo-labels the user made with real
  VLM outputs (`ago pseudo-labels --segmenter files --embedder files`); nothing is generated for it.

Seeds (`ExperimentProfile.seeds`): every closed-world and open-world run is trained once per seed
(seed 0 keeps the plain name, seed s > 0 is `<name>-seed<s>`); few-shot run `fewshot/<variant>/seed<s>`
fine-tunes the pretraining run of seed s on the k-shot subset drawn with seed s. The report prints the
mean and every seed's value and says which differences are above the seed spread.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from ago_runtime.errors import AgoInputError

PROFILES = ("tiny", "cpu", "full")
# loss variants of the paradigm ablation, in the paper's order
PARADIGMS = ("align", "grounding", "grounding+align", "ago")
FEWSHOT_VARIANTS = ("align", "grounding", "ago")
# the open-world recipe (issue "Open world that works", docs/training.md "Matter of no training class")
OW_RECIPE = {"align_center": True, "occ_unlabelled_weight": 4.0, "w_unlabelled_uniform": 0.5}
# diagnostic temperatures for the adapted branch's logits (Tab. 4 extra rows; chosen on val: optimistic)
ADAPTED_SCALES = (3.0, 10.0, 30.0)


# the label space (prompt file) of each pseudo-label space, per dataset
PROMPTS = {"nuscenes": {"cw": "cw", "ow_pretrain": "ow_pretrain", "ow": "ow"},
           "waymo": {"cw": "waymo/cw_waymo", "ow_pretrain": "waymo/ow_waymo_pretrain", "ow": "waymo/ow_waymo"}}
# the pseudo-label space a run of each setting trains on
SETTING_SPACE = {"cw": "cw", "ow": "ow_pretrain", "fewshot": "ow"}
# Tab. H's pretraining stage is scored on the pretraining classes (cycle whole) + the unknown ones
WAYMO_PRETRAIN_EVAL = "waymo/ow_waymo_pretrain_eval"


def shipped_prompts(name: str) -> str:
    """The path of the shipped prompt file `name` (e.g. "waymo/ow_waymo"): prompts/<name>.txt."""
    from ago_runtime.vocab.prompts import PROMPTS_DIR

    return str(PROMPTS_DIR / f"{name}.txt")


# profile keys added after experiment folders were made: a saved profile without them still matches
ADDED_KEYS = ("waymo",)


@dataclass
class WaymoSetting:
    """The Occ3D-Waymo part of a profile (Tab. G and H): its data and pseudo-label folders (relative to the
    experiments folder unless absolute), `ago synth` options (with `rig: waymo`) and the ModelConfig changes
    of its runs. The canvas: Waymo's front cameras are 3:2 (1920x1280), so each profile's Waymo canvas is 3:2 with
    the height of its nuScenes canvas rounded to a multiple of 64 (both sides then multiples of 32, as the
    backbone needs): tiny 96x64, cpu 288x192, full 1440x960 (nuScenes 96x64, 352x192, 1600x928). The side
    cameras' shorter images fill the canvas' upper part at the same scale (Preprocess.camera_sizes)."""

    data: str = "synth_waymo"
    synth: dict = field(default_factory=lambda: {"rig": "waymo", "scenes": 12, "frames": 12, "image-size": "576x384",
                                                 "grid": "200x200x16", "seed": 0, "val-fraction": 0.25})
    pseudo: dict = field(default_factory=lambda: {"cw": "pseudo_waymo_cw", "ow_pretrain": "pseudo_waymo_ow_pretrain",
                                                  "ow": "pseudo_waymo_ow"})
    model: dict = field(default_factory=lambda: {"image_width": 288, "image_height": 192})


def profile_differences(saved: dict, mine: dict) -> list[str]:
    """The keys in which two profiles (as dicts) differ; a key of ADDED_KEYS that `saved` lacks is no difference
    (the folder was made before that key existed, and holds nothing of it)."""
    keys = set(saved) | set(mine)
    return sorted(k for k in keys if saved.get(k) != mine.get(k) and not (k in ADDED_KEYS and k not in saved))


@dataclass
class ExperimentProfile:
    name: str = "cpu"
    # ---- data (generated with `ago synth` / `ago pseudo-labels` unless external_data) ----
    external_data: bool = False
    data: str = "synth"                       # dataset root, relative to the experiments folder unless absolute
    synth: dict = field(default_factory=lambda: {"scenes": 12, "frames": 12, "image-size": "704x396",
                                                 "grid": "200x200x16", "seed": 0, "val-fraction": 0.25})
    pseudo_grid: str = "100x100x8"            # the model's grid too (the runs of the committed tables used 0.8 m)
    pseudo_carve: str = "all"                 # `ago pseudo-labels --carve` (the committed tables' runs used all)
    sweeps: int = 10                 # keyframes superimposed per pseudo-label sample (`ago pseudo-labels --keyframes`)
    interval: int = 1
    pseudo: dict = field(default_factory=lambda: {"cw": "pseudo_cw", "ow_pretrain": "pseudo_ow_pretrain",
                                                  "ow": "pseudo_ow"})
    # ---- training ----
    train_preset: str = "cpu"                 # TrainConfig preset every run starts from
    steps: int | None = 1000                  # optimiser steps per cw / ow run (None: the preset's epochs)
    fewshot_steps: int | None = 150           # optimiser steps per few-shot fine-tuning (None: fewshot_epochs)
    fewshot_epochs: int = 12
    k: int = 5                                # shots per class
    seeds: tuple[int, ...] = (0, 1)           # training seeds: every run repeated per seed (module docstring)
    # LossConfig overrides of every open-world and few-shot run (the open-world recipe; {} = the paper's losses)
    ow_loss: dict = field(default_factory=lambda: dict(OW_RECIPE))
    train_split: str = "train"
    train_set: dict = field(default_factory=dict)  # extra TrainConfig overrides for every run
    # ---- evaluation ----
    eval_split: str = "val"
    eval_max_frames: int | None = None
    render_frames: int = 2                    # val frames drawn in the voxel-render figure
    # ---- Occ3D-Waymo (Tab. G and H) ----
    waymo: WaymoSetting = field(default_factory=WaymoSetting)

    @classmethod
    def preset(cls, name: str) -> "ExperimentProfile":
        if name == "cpu":
            return cls()
        if name == "tiny":
            return cls(name="tiny", synth={"scenes": 3, "frames": 3, "image-size": "192x128", "grid": "40x40x8",
                                           "seed": 3, "val-fraction": 0.34},
                       pseudo_grid="20x20x4", sweeps=2, train_preset="tiny", steps=2, fewshot_steps=1, k=1,
                       seeds=(0, 1), render_frames=1,
                       waymo=WaymoSetting(synth={"rig": "waymo", "scenes": 3, "frames": 3, "image-size": "192x128",
                                                 "grid": "40x40x8", "seed": 3, "val-fraction": 0.34},
                                          model={"image_width": 96, "image_height": 64}))
        if name == "full":
            return cls(name="full", external_data=True, data="data/nuscenes", synth={},
                       pseudo_grid="200x200x16", sweeps=30, interval=2,
                       pseudo={"cw": "data/nuscenes-pseudo-cw", "ow_pretrain": "data/nuscenes-pseudo-ow-pretrain",
                               "ow": "data/nuscenes-pseudo-ow"},
                       train_preset="full", steps=None, fewshot_steps=None, fewshot_epochs=12, k=100,
                       seeds=(0, 1, 2), ow_loss={}, render_frames=3,
                       waymo=WaymoSetting(data="data/occ3d-waymo", synth={},
                                          pseudo={"cw": "data/waymo-pseudo-cw",
                                                  "ow_pretrain": "data/waymo-pseudo-ow-pretrain",
                                                  "ow": "data/waymo-pseudo-ow"},
                                          model={"image_width": 1440, "image_height": 960}))
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
    dataset: str = "nuscenes"                 # "nuscenes" | "waymo" (which data, pseudo-labels, label spaces)

    @property
    def space(self) -> str:
        """The pseudo-label space it trains on: "cw", "ow_pretrain" or "ow"."""
        return SETTING_SPACE[self.setting]

    @property
    def prompts(self) -> str:
        return PROMPTS[self.dataset][self.space]


def _variant_loss(variant: str) -> tuple:
    return (("variant", variant),)


def seeded(name: str, seed: int) -> str:
    """The run name of `name` trained with `seed` (seed 0 keeps the plain name)."""
    return name if seed == 0 else f"{name}-seed{seed}"


def cw_run(variant: str = "ago", seed: int = 0, **loss) -> RunSpec:
    suffix = "".join(f"-{k.replace('use_', 'no-')}" for k, v in loss.items() if v is False)
    return RunSpec(seeded(f"cw/{variant}{suffix}", seed), "cw", _variant_loss(variant) + tuple(sorted(loss.items())),
                   seed=seed)


def ow_run(variant: str = "ago", adapter_depth: int | None = None, align_loss: str | None = None,
           seed: int = 0) -> RunSpec:
    name, loss, model = f"ow/{variant}", _variant_loss(variant), ()
    if adapter_depth is not None and adapter_depth != 2:
        name, model = f"{name}-adapter{adapter_depth}", (("adapter_depth", adapter_depth),)
    if align_loss is not None and align_loss != "cosine":
        name, loss = f"{name}-{align_loss}", loss + (("align_loss", align_loss),)
    return RunSpec(seeded(name, seed), "ow", loss, model, seed=seed)


def fewshot_run(variant: str, seed: int) -> RunSpec:
    """Few-shot repeat `seed`: the pretraining run of that seed, fine-tuned on the k-shot subset of that seed."""
    pre = ow_run(variant, seed=seed)
    return RunSpec(f"fewshot/{variant}/seed{seed}", "fewshot", pre.loss, pre.model, init_from=pre.name, seed=seed)


def waymo_run(setting: str, seed: int = 0) -> RunSpec:
    """An Occ3D-Waymo run (Tab. G / H), always the ago variant: `waymo/cw/ago`, `waymo/ow/ago` (each per seed as
    `seeded` names it) or `waymo/fewshot/ago/seed<s>`, which fine-tunes `waymo/ow/ago` of seed s."""
    if setting == "fewshot":
        pre = waymo_run("ow", seed)
        return RunSpec(f"waymo/fewshot/ago/seed{seed}", "fewshot", pre.loss, init_from=pre.name, seed=seed,
                       dataset="waymo")
    return RunSpec(seeded(f"waymo/{setting}/ago", seed), setting, _variant_loss("ago"), seed=seed, dataset="waymo")
