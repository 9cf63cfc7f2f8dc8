"""CLI verbs `ago train`, `ago eval`, `ago open-world` (torch is imported inside the commands).

    ago train --config cpu|tiny|full|cfg.json [--set key=value ...] [--resume] [--out DIR]
    torchrun --nproc_per_node 2 -m ago_runtime.cli train --config ...      (DDP; gloo on CPU, nccl on GPU)
    ago calibrate RUN                       (re-fit the identifier's calibration of RUN/last.pt, no training)
    ago eval --ckpt RUN/last.pt --data DIR [--split val] [--prompts FILE] [--identifier ...] [--out DIR]
    ago open-world --stage pretrain|zeroshot|fewshot|all --config cpu --data DIR \
        --pseudo-pretrain DIR --pseudo-full DIR [--k 100] [--seeds 0,1,2] [--out DIR]
"""

from __future__ import annotations

import json
from enum import Enum
from pathlib import Path
from typing import List, Optional

import typer

from ago_runtime.predict.decision import Identifier

from .pseudo.cli import Carve, Moving
from .train_real import RealRecipe

REAL = RealRecipe()   # `ago train-real`'s option defaults are the recipe's


class OpenWorldStage(str, Enum):
    """`ago open-world --stage`."""

    PRETRAIN = "pretrain"
    ZEROSHOT = "zeroshot"
    FEWSHOT = "fewshot"
    ALL = "all"


def _config(config: str, sets: Optional[List[str]], out: Optional[str], data: Optional[str] = None,
            pseudo: Optional[str] = None, prompts: Optional[str] = None, text_encoder: Optional[str] = None):
    from .train_config import TrainConfig

    cfg = TrainConfig.from_name_or_path(config).with_overrides(sets)
    extra = []
    for key, value in (("out", out), ("data", data), ("pseudo", pseudo), ("prompts", prompts),
                       ("text_encoder", text_encoder)):
        if value is not None:
            extra.append(f"{key}={json.dumps(value)}")
    return cfg.with_overrides(extra)


def _prompts_from_pseudo(cfg, config: str):
    """`cfg` with the prompt file its pseudo-labels were made with, when the user named none (no --prompts, no
    --set prompts=, a preset whose prompts is only a default): the label space follows the data. A JSON config's
    own `prompts` is kept. The pseudo-label folder records its prompt file (meta.json label_space.prompt_file) and
    keeps a copy (label_space.txt), used when the recorded file is gone and the table is a shipped one."""
    from .pseudo.generate import PseudoLabelDir
    from .train_config import PRESETS

    if config not in PRESETS or not cfg.pseudo or not (Path(cfg.pseudo) / "meta.json").is_file():
        return cfg
    ls = PseudoLabelDir(cfg.pseudo).meta.get("label_space") or {}
    recorded = ls.get("prompt_file")
    if recorded and Path(recorded).is_file():
        chosen = recorded
    elif "class_table" not in ls or isinstance(ls.get("class_table"), str):   # a shipped table: the copy reads alone
        chosen = str(Path(cfg.pseudo) / "label_space.txt")
    else:
        return cfg
    typer.echo(f"note: using --prompts {chosen} (the prompt file the pseudo-labels in {cfg.pseudo} were made with)")
    return cfg.with_overrides([f"prompts={json.dumps(chosen)}"])


def register(app: typer.Typer) -> None:
    @app.command("train")
    def train_cmd(
        config: str = typer.Option("cpu", "--config", help="preset (tiny, cpu, full) or a JSON config file"),
        sets: Optional[List[str]] = typer.Option(None, "--set", help="override a config value: key=value "
                                                  "(dotted keys for model./loss., JSON values)"),
        resume: bool = typer.Option(False, "--resume", help="continue from <out>/last.pt exactly"),
        out: Optional[str] = typer.Option(None, "--out", help="output folder (checkpoints, log, config)"),
        data: Optional[str] = typer.Option(None, "--data", help="dataset root"),
        pseudo: Optional[str] = typer.Option(None, "--pseudo", help="pseudo-label folder (ago pseudo-labels)"),
        prompts: Optional[str] = typer.Option(None, "--prompts", help="prompt file (label space)"),
        text_encoder: Optional[str] = typer.Option(None, "--text-encoder", help="a CLIP save_pretrained folder: its "
                                                   "text tower makes the banks (the paper's space; default MiniLM; "
                                                   "docs/prompts.md)"),
        print_config: bool = typer.Option(False, "--print-config", help="print the resolved config and exit"),
    ):
        """Train AGO from pseudo-labels (single process, or DDP under torchrun)."""
        from ago_runtime.errors import require_torch

        require_torch("train")
        # the folder's absolute path: export and eval find it again from another working directory
        cfg = _config(config, sets, out, data, pseudo, prompts, str(Path(text_encoder).resolve()) if text_encoder else None)
        if prompts is None and not any(a.split("=", 1)[0].strip() == "prompts" for a in sets or []):
            cfg = _prompts_from_pseudo(cfg, config)
        if cfg.text_encoder is not None:   # a wrong folder is one line before anything runs
            from ago_runtime.vocab.model_folder import read_model_config

            read_model_config(cfg.text_encoder, "--text-encoder" if text_encoder else "text_encoder", "clip")
        if print_config:
            typer.echo(json.dumps(cfg.to_dict(), indent=2))
            return
        from ago_runtime.outputs import check_output_dir

        check_output_dir(cfg.out, "--out (config out)")
        from .trainer import train

        r = train(cfg, resume=resume)
        if r["last"]:
            typer.echo(f"trained {r['step']} steps; checkpoint {r['last']}")

    @app.command("train-real")
    def train_real_cmd(
        dataroot: Path = typer.Argument(..., help="a nuScenes dataroot (official, or a trimmed extract)"),
        out: Path = typer.Argument(..., help="output folder: OUT/bundle, OUT/train_real.json, OUT/work"),
        max_scenes: int = typer.Option(REAL.max_scenes, "--max-scenes", min=1, help="real scenes used at most (evenly spaced)"),
        steps: int = typer.Option(REAL.steps, "--steps", min=1, help="training steps (the val block picks a snapshot)"),
        town_scenes: int = typer.Option(REAL.town_scenes, "--town-scenes", min=2, help="synthetic town mixed in: scenes"),
        town_frames: int = typer.Option(REAL.town_frames, "--town-frames", min=2, help="synthetic town: keyframes per scene"),
        preset: str = typer.Option(REAL.preset, "--preset", help="training preset (cpu; full on a GPU)"),
        jobs: int = typer.Option(REAL.jobs, "--jobs", min=1, help="worker processes for synth and pseudo-labels"),
        carve: Carve = typer.Option(Carve(REAL.carve), "--carve", help="pseudo-labels' free-space rule (`ago pseudo-labels "
                                    "--carve`): all or grazing"),
        moving: Moving = typer.Option(Moving(REAL.moving), "--moving", help="pseudo-labels' moving classes (`ago "
                                      "pseudo-labels --moving`): aggregate, keyframe or track"),
    ):
        """A nuScenes dataroot -> OUT/bundle: time split, synthetic town, pseudo-labels, mixed training, length
        chosen on a val block, export (docs/training.md, "Training on your own data"); resumes."""
        from ago_runtime.errors import require_torch

        require_torch("train-real")
        from ago_runtime.outputs import check_output_dir

        check_output_dir(out, "OUT")
        from .train_real import train_real

        train_real(dataroot, out, RealRecipe(max_scenes=max_scenes, steps=steps, town_scenes=town_scenes,
                                             town_frames=town_frames, preset=preset, jobs=jobs, carve=carve.value,
                                             moving=moving.value),
                   say=lambda s: typer.echo(s))

    @app.command("calibrate")
    def calibrate_cmd(
        run: Path = typer.Argument(..., help="a finished `ago train` folder (config.json, last.pt)"),
    ):
        """Re-fit the open-world identifier's calibration of RUN/last.pt on its training frames (no training)."""
        from ago_runtime.errors import require_torch

        require_torch("calibrate")
        from .trainer import recalibrate

        cal = recalibrate(run)
        typer.echo(f"calibrated {run / 'last.pt'}: scale_main {cal.scale_main:.3f}, scale_adapted "
                   f"{cal.scale_adapted:.3f} ({cal.adapted_rule or 'nll'}), adapted statistics from "
                   f"{cal.adapted_voxels or 0} voxels")

    @app.command("eval")
    def eval_cmd(
        ckpt: Path = typer.Option(..., "--ckpt", help="checkpoint (.pt) from ago train"),
        data: Path = typer.Option(..., "--data", help="dataset root with Occ3D gts/"),
        split: str = typer.Option("val", "--split", help="split of the dataset's splits.json, or all"),
        prompts: Optional[str] = typer.Option(None, "--prompts", help="prompt file (default: the checkpoint's)"),
        identifier: Optional[Identifier] = typer.Option(None, "--identifier",
                                                        help="default: none in the closed world, min-entropy "
                                                             "with unknown classes"),
        out: Optional[Path] = typer.Option(None, "--out", help="folder for metrics.json / metrics.md "
                                                               "(default: <ckpt folder>/eval-<split>)"),
        gts: Optional[str] = typer.Option(None, "--gts", help="Occ3D gts root when not <data>/gts"),
        max_frames: Optional[int] = typer.Option(None, "--max-frames", min=1,
                                                 help="score only the first N frames of the split (default: all)"),
        device: str = typer.Option("auto", "--device", help="auto | cpu | cuda | cuda:N"),
        readout: str = typer.Option("model", "--readout", help="model: predict on the model grid, repeated up "
                                    "to the GT grid (what a bundle does); gt: read the TPV planes at the GT "
                                    "grid's voxel centres (finer surfaces, 8x the voxels)"),
    ):
        """Score a checkpoint against Occ3D GT (per-class IoU, mIoU, known/unknown mIoU)."""
        from ago_runtime.errors import require_torch

        require_torch("eval")
        from ago_runtime.errors import AgoInputError
        from ago_runtime.outputs import check_output_dir

        from .config_checks import check_device
        from .evaluate import evaluate

        check_device(device)
        if gts is not None and not Path(gts).is_dir():   # before the frames are predicted, not after
            raise AgoInputError("--gts", f"{gts}: Occ3D gts folder not found")
        out = out if out is not None else Path(ckpt).parent / f"eval-{split}"
        check_output_dir(out, "--out")
        r = evaluate(ckpt, data, split=split, prompts=prompts, identifier=identifier.value if identifier else None,
                     out=out, gts=gts,
                     max_frames=max_frames, device=device, readout=readout)
        subs = ", ".join(f"{k} {v}" for k, v in r["subsets"].items())
        typer.echo(f"mIoU {r['mIoU']} (%){'; ' + subs if subs else ''}; written {out}/metrics.json, metrics.md")

    @app.command("open-world")
    def open_world_cmd(
        stage: OpenWorldStage = typer.Option(OpenWorldStage.ALL, "--stage", help="which stages to run"),
        config: str = typer.Option("cpu", "--config", help="base training preset or JSON file"),
        sets: Optional[List[str]] = typer.Option(None, "--set", help="override a base config value"),
        data: Optional[str] = typer.Option(None, "--data", help="dataset root"),
        pseudo_pretrain: Path = typer.Option(..., "--pseudo-pretrain",
                                             help="pseudo-labels made with prompts/ow_pretrain.txt"),
        pseudo_full: Optional[Path] = typer.Option(None, "--pseudo-full",
                                                   help="pseudo-labels made with prompts/ow.txt (few-shot)"),
        k: int = typer.Option(100, "--k", min=1, help="shots per class"),
        seeds: str = typer.Option("0,1,2", "--seeds", help="comma-separated few-shot seeds"),
        fewshot_epochs: Optional[int] = typer.Option(None, "--fewshot-epochs", min=1,
                                                     help="fine-tuning epochs (default 12; 1 for tiny)"),
        eval_split: str = typer.Option("val", "--eval-split"),
        identifier: Identifier = typer.Option(Identifier.MIN_ENTROPY, "--identifier"),
        out: Path = typer.Option(Path("runs/open-world"), "--out"),
    ):
        """The paper's open-world protocol: pretrain (5 classes), zero-shot and few-shot on 15 classes."""
        from ago_runtime.errors import require_torch
        from ago_runtime.errors import AgoInputError

        require_torch("open-world")
        from ago_runtime.outputs import check_output_dir


        from .open_world import OpenWorldConfig, run_open_world

        stage, identifier = stage.value, identifier.value
        check_output_dir(out, "--out")
        try:   # each option's own problem first: --seeds, the folders, then what the stage needs
            seed_list = tuple(int(s) for s in seeds.split(",") if s.strip())
        except ValueError:
            raise AgoInputError("--seeds", f"must be comma-separated integers, got {seeds!r}") from None
        if not seed_list or min(seed_list) < 0:
            raise AgoInputError("--seeds", f"needs one or more integers >= 0, got {seeds!r}")
        for option, folder in (("--pseudo-pretrain", pseudo_pretrain), ("--pseudo-full", pseudo_full)):
            if folder is not None and not Path(folder).is_dir():
                raise AgoInputError(option, f"{folder}: pseudo-label folder not found")
        base = _config(config, sets, None, data)
        if stage in ("fewshot", "all") and pseudo_full is None:
            raise AgoInputError("--pseudo-full", "is needed for the few-shot stage (--stage fewshot or all)")
        ow = OpenWorldConfig(base=base, pseudo_pretrain=str(pseudo_pretrain),
                             pseudo_full=str(pseudo_full) if pseudo_full else "", out=str(out), k=k,
                             seeds=seed_list, eval_split=eval_split, identifier=identifier,
                             fewshot_epochs=fewshot_epochs if fewshot_epochs is not None else
                             (1 if base.name == "tiny" else 12))
        run_open_world(ow, stage=stage)
        typer.echo(f"written {out}/results.json and {out}/results.md")
