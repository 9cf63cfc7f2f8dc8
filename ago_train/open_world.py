"""The AGO paper's open-world protocol in three stages (`ago open-world --stage ...`).

1. pretrain: train on the 5-class label space `prompts/ow_pretrain.txt` (pedestrian, driveable
   surface, sidewalk, vehicle, cycle) from pseudo-labels made with that label space
   (`pseudo_pretrain`), `epochs` as the base TrainConfig -> `<out>/pretrain/last.pt`.
2. zeroshot: evaluate that checkpoint on the 15-class space `prompts/ow.txt` (no retraining): the
   known classes are the Occ3D classes the pretraining classes cover (`@known` is set from them
   here), the unknown ones are the rest; open-world identifier "min-entropy" by default
   -> `<out>/zeroshot/metrics.{json,md}`.
3. fewshot: for each seed, pick a k-shot subset of the training frames — frames in a seeded random
   order, a frame is taken when it holds (in its `ow.txt` pseudo-labels, `pseudo_full`) a class that is
   still in fewer than k taken frames, until every class that occurs at all is in >= k frames —
   fine-tune the pretrained weights on it (`fewshot_epochs`, 12 in the paper, fresh optimiser and
   schedule) with the 15-class label space, and evaluate like stage 2. Results averaged over seeds.

Everything lands in `<out>/results.json` and `<out>/results.md` (each stage adds its part).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from ago_runtime.atomic import write_json, write_text
from ago_runtime.errors import AgoInputError
from ago_runtime.vocab.prompts import parse_prompt_file, resolve_prompt_file

from .dataset import PseudoLabelSet
from .train_config import TrainConfig

STAGES = ("pretrain", "zeroshot", "fewshot", "all")


@dataclasses.dataclass
class OpenWorldConfig:
    base: TrainConfig                     # data, model, loss, optimiser; prompts/pseudo are set per stage
    pseudo_pretrain: str                  # pseudo-labels made with prompts/ow_pretrain.txt
    pseudo_full: str                      # pseudo-labels made with prompts/ow.txt (few-shot stage)
    out: str = "runs/open-world"
    pretrain_prompts: str = "ow_pretrain"
    eval_prompts: str = "ow"
    eval_split: str = "val"
    identifier: str = "min-entropy"
    k: int = 100                          # shots: each class in >= k frames of the subset (paper: 100)
    seeds: tuple[int, ...] = (0, 1, 2)
    fewshot_epochs: int = 12
    eval_max_frames: int | None = None


def open_world_label_space(eval_prompts: str, pretrain_prompts: str):
    """The evaluation label space with `known` = its classes whose Occ3D ids the pretraining space covers."""
    space = parse_prompt_file(eval_prompts)
    pre = parse_prompt_file(pretrain_prompts)
    covered = {i for c in pre.classes for i in c.occ3d_ids}
    space.known = {c.name for c in space.classes if c.occ3d_ids and set(c.occ3d_ids) <= covered}
    return space


def paper_split(eval_prompts: str, pretrain_prompts: str) -> tuple[list[str], list[str]]:
    """The AGO paper's known / unknown split of the evaluation classes after pretraining (its Tab. 2):
    a class is known only when one pretraining class stands for exactly its Occ3D ids; the classes that
    refine a pretraining super-category ("vehicle" -> car, bus, ...) count as unknown, like the classes
    pretraining never saw. -> (known, unknown) class names of the evaluation space, in its order (classes
    without Occ3D ids are left out). `open_world_label_space` is this driver's split, where a refined
    class counts as known."""
    space = parse_prompt_file(eval_prompts)
    pre = parse_prompt_file(pretrain_prompts)
    exact = {frozenset(c.occ3d_ids) for c in pre.classes if c.occ3d_ids}
    scored = [c for c in space.classes if c.occ3d_ids]
    known = [c.name for c in scored if frozenset(c.occ3d_ids) in exact]
    return known, [c.name for c in scored if c.name not in known]


def known_prompt_file(ow: OpenWorldConfig, out: Path) -> Path:
    """A copy of the evaluation prompt file with an `@known:` line (unless it has one)."""
    src = resolve_prompt_file(ow.eval_prompts)
    space = open_world_label_space(str(src), ow.pretrain_prompts)
    text = src.read_text(encoding="utf-8")
    if not any(line.strip().startswith("@known") for line in text.splitlines()):
        text = f"@known: {', '.join(c for c in space.class_names if c in space.known)}\n" + text
    path = out / f"{src.stem}_known.txt"
    write_text(path, text)
    return path


def select_kshot(pseudo: PseudoLabelSet, frames: list[tuple[str, str]], num_classes: int, k: int,
                 seed: int) -> tuple[list[str], dict[int, int]]:
    """Sample tokens of a k-shot subset and the count of frames per class in it (see module docstring)."""
    present = []
    for scene, token in frames:
        sem = pseudo.labels(scene, token)
        present.append(set(int(c) for c in np.unique(sem) if c < num_classes))
    occurring = set().union(*present) if present else set()
    counts = {c: 0 for c in range(num_classes)}
    chosen: list[str] = []
    for i in np.random.default_rng(seed).permutation(len(frames)):
        if all(counts[c] >= k for c in occurring):
            break
        if any(counts[c] < k for c in present[i]):
            chosen.append(frames[i][1])
            for c in present[i]:
                counts[c] += 1
    return chosen, counts


def _summary_row(result: dict) -> dict:
    return {"mIoU": result["mIoU"], **{f"mIoU_{k}": v for k, v in result["subsets"].items()},
            "iou": result["metric"]["iou"]}


def _mean_rows(rows: list[dict]) -> dict:
    def mean(vals):
        vals = [v for v in vals if v is not None]
        return round(float(np.mean(vals)), 2) if vals else None

    keys = [k for k in rows[0] if k != "iou"]
    out = {k: mean([r[k] for r in rows]) for k in keys}
    out["iou"] = {c: mean([r["iou"][c] for r in rows]) for c in rows[0]["iou"]}
    return out


def run_open_world(ow: OpenWorldConfig, stage: str = "all", quiet: bool = False) -> dict:
    from .evaluate import evaluate
    from .sources import open_split
    from .trainer import train

    if stage not in STAGES:
        raise AgoInputError(None, f"unknown stage {stage!r}; choose one of {list(STAGES)}")
    out = Path(ow.out)
    results_path = out / "results.json"
    results = json.loads(results_path.read_text()) if results_path.is_file() else {}
    pre_ckpt = out / "pretrain" / "last.pt"

    if stage in ("pretrain", "all"):
        cfg = dataclasses.replace(ow.base, prompts=ow.pretrain_prompts, pseudo=ow.pseudo_pretrain,
                                  out=str(out / "pretrain"), init_from=None, frame_tokens=None)
        r = train(cfg, quiet=quiet)
        results["pretrain"] = {"checkpoint": str(pre_ckpt), "steps": r["step"],
                               "final_loss": r["losses"][-1] if r["losses"] else None}
        write_json(results_path, results)

    eval_prompt = known_prompt_file(ow, out)
    if stage in ("zeroshot", "all"):
        if not pre_ckpt.is_file():
            raise AgoInputError(pre_ckpt, "no pretrained checkpoint; run --stage pretrain first")
        r = evaluate(pre_ckpt, ow.base.data, split=ow.eval_split, prompts=str(eval_prompt),
                     identifier=ow.identifier, out=out / "zeroshot", gts=ow.base.gts,
                     max_frames=ow.eval_max_frames, quiet=quiet)
        results["zeroshot"] = _summary_row(r)
        write_json(results_path, results)

    if stage in ("fewshot", "all"):
        if not pre_ckpt.is_file():
            raise AgoInputError(pre_ckpt, "no pretrained checkpoint; run --stage pretrain first")
        space = parse_prompt_file(ow.eval_prompts)
        pseudo = PseudoLabelSet.open(ow.pseudo_full)
        ds, indices = open_split(ow.base.data, ow.base.gts, ow.base.train_split)
        if ow.base.max_frames is not None:
            indices = indices[: ow.base.max_frames]
        frames = [(ds.scene_of(i), ds.sample_tokens[i]) for i in indices]
        rows, runs = [], []
        for seed in ow.seeds:
            tokens, counts = select_kshot(pseudo, frames, space.num_classes, ow.k, seed)
            if not tokens:
                raise AgoInputError(ow.pseudo_full, "no frame holds any class: cannot pick a few-shot subset")
            run_dir = out / "fewshot" / f"seed{seed}"
            cfg = dataclasses.replace(ow.base, prompts=ow.eval_prompts, pseudo=ow.pseudo_full, out=str(run_dir),
                                      init_from=str(pre_ckpt), frame_tokens=tokens, epochs=ow.fewshot_epochs,
                                      max_frames=None, seed=seed)
            train(cfg, quiet=quiet)
            r = evaluate(run_dir / "last.pt", ow.base.data, split=ow.eval_split, prompts=str(eval_prompt),
                         identifier=ow.identifier, out=run_dir / "eval", gts=ow.base.gts,
                         max_frames=ow.eval_max_frames, quiet=quiet)
            rows.append(_summary_row(r))
            runs.append({"seed": seed, "frames": len(tokens),
                         "class_frames": {space.class_names[c]: n for c, n in counts.items()}, **rows[-1]})
        results["fewshot"] = {"k": ow.k, "seeds": list(ow.seeds), "epochs": ow.fewshot_epochs,
                              "mean": _mean_rows(rows), "runs": runs}
        write_json(results_path, results)

    write_text(out / "results.md", results_markdown(results))
    return results


def results_markdown(results: dict) -> str:
    lines = ["# Open-world protocol results", ""]
    if "pretrain" in results:
        p = results["pretrain"]
        lines += [f"Stage 1 (pretrain on ow_pretrain): {p['steps']} steps, final loss {p['final_loss']}.", ""]
    table = []
    if "zeroshot" in results:
        table.append(("zero-shot", results["zeroshot"]))
    if "fewshot" in results:
        f = results["fewshot"]
        table.append((f"{f['k']}-shot (mean of {len(f['seeds'])} seeds)", f["mean"]))
    if table:
        classes = list(table[0][1]["iou"])
        lines.append("| stage | mIoU | known | unknown | " + " | ".join(classes) + " |")
        lines.append("|---|---:|---:|---:|" + "---:|" * len(classes))

        def fmt(v):
            return "n/a" if v is None else f"{v:.2f}"

        for name, row in table:
            lines.append(f"| {name} | {fmt(row.get('mIoU'))} | {fmt(row.get('mIoU_known'))} | "
                         f"{fmt(row.get('mIoU_unknown'))} | " + " | ".join(fmt(row["iou"].get(c)) for c in classes) + " |")
    return "\n".join(lines) + "\n"
