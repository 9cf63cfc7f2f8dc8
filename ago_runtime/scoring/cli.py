"""CLI verb `ago metric`: the Occ3D mIoU of predictions against ground truth.

`ago metric --pred DIR --gt DIR [--json out.json] [--md out.md] [--subset NAME=c1,c2]`
    evaluates predictions against Occ3D ground truth (see `ago_runtime.scoring.metric`).
    GT: `<gt>/<scene>/<token>/labels.npz` (searched recursively). Predictions, matched by sample
    token: `<pred>/<scene>/<token>/labels.npz`, `<pred>/<token>/labels.npz` or `<pred>/<token>.npz`,
    each with a `semantics` array at GT resolution or an integer fraction of it (upsampled by
    nearest-neighbour repetition; evaluation is at GT resolution).
`--prompts FILE` scores in that prompt file's label space, as the torch evaluation (`ago eval`) does:
    GT voxels of Occ3D classes no prompt covers are ignored, predictions are matched by class name,
    mIoU is over the file's classes, and its @known line gives "known" / "unknown" subsets.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import numpy as np

import typer

from ago_runtime.errors import AgoInputError
from ago_runtime.formats.occ3d import load_semantics
from ago_runtime.scoring.metric import _pct, to_gt_resolution


def find_gt_files(gt_root: Path) -> dict[str, Path]:
    """sample token -> GT labels.npz under `gt_root` (Occ3D layout `<scene>/<token>/labels.npz`)."""
    if not gt_root.is_dir():
        raise AgoInputError(gt_root, "ground-truth folder not found")
    files = sorted(gt_root.rglob("labels.npz"))
    if not files:
        raise AgoInputError(gt_root, "no labels.npz found (expected <scene>/<token>/labels.npz)")
    out: dict[str, Path] = {}
    for f in files:
        token = f.parent.name
        if token in out:
            raise AgoInputError(f, f"sample token {token} appears twice (also {out[token]})")
        out[token] = f
    return out


def find_prediction(pred_root: Path, gt_file: Path) -> Path | None:
    """The prediction file for the GT file's sample token, or None."""
    token, scene = gt_file.parent.name, gt_file.parent.parent.name
    for cand in (pred_root / scene / token / "labels.npz", pred_root / token / "labels.npz",
                 pred_root / f"{token}.npz"):
        if cand.is_file():
            return cand
    return None


def parse_subsets(items: list[str] | None, class_names: list[str]) -> dict[str, list[str]]:
    """`NAME=c1,c2` or `c1,c2` (named by its classes) -> {name: [classes]}; unknown classes refused."""
    out: dict[str, list[str]] = {}
    for item in items or []:
        name, _, rest = item.partition("=") if "=" in item else (item, "", item)
        classes = [c.strip() for c in rest.split(",") if c.strip()]
        bad = [c for c in classes if c not in class_names]
        if not classes or bad:
            raise AgoInputError(None, f"--subset {item!r}: unknown class(es) {bad or '(none given)'}; "
                                      f"known: {', '.join(class_names)}")
        out[name.strip()] = classes
    return out


def prediction_in_space(path: Path, sem: np.ndarray, names: list[str]) -> np.ndarray:
    """A prediction file's labels as indices of `names` (a label space's classes then "free"), matched by
    class name: the file's `bank_semantics` / `bank_class_names` when present (ago infer with a bank
    whose classes are Occ3D classes), else its `semantics` / `class_names`."""
    with np.load(path, allow_pickle=False) as z:
        if "bank_semantics" in z.files and "bank_class_names" in z.files:
            sem, file_names = np.asarray(z["bank_semantics"]), [str(c) for c in z["bank_class_names"]]
        elif "class_names" in z.files:
            file_names = [str(c) for c in z["class_names"]]
        else:
            raise AgoInputError(path, "--prompts needs prediction files with class names (written by ago infer)")
    index = {c: i for i, c in enumerate(names)}
    lut = np.full(max(len(file_names), 1), 255, np.int64)
    for i, c in enumerate(file_names):
        lut[i] = index.get(c, 255)
    present = np.unique(sem)
    if present.size and present.max() >= len(file_names):
        raise AgoInputError(path, f"labels up to {int(present.max())} but only {len(file_names)} class names")
    outside = [file_names[v] for v in present if lut[v] == 255]
    if outside:
        raise AgoInputError(path, f"predicts {outside[:3]}, not classes of the --prompts file")
    return lut[sem].astype(np.uint8)


def register(app: typer.Typer) -> None:
    @app.command("metric")
    def metric(
        pred: Path = typer.Option(..., "--pred",
                                  help="folder of predictions (<scene>/<token>/labels.npz or <token>.npz)"),
        gt: Path = typer.Option(..., "--gt", help="Occ3D ground-truth folder (<scene>/<token>/labels.npz)"),
        json_out: Optional[Path] = typer.Option(None, "--json", help="write the summary as JSON"),
        md_out: Optional[Path] = typer.Option(None, "--md", help="write the markdown table"),
        subset: Optional[List[str]] = typer.Option(None, "--subset",
                                                   help="extra mIoU over classes: NAME=c1,c2 (repeatable)"),
        allow_missing: bool = typer.Option(False, "--allow-missing", help="skip GT frames with no prediction"),
        no_mask: bool = typer.Option(False, "--no-mask", help="score every voxel, not only mask_camera"),
        prompts: Optional[Path] = typer.Option(
            None, "--prompts", help="score in this prompt file's label space (as `ago eval` does): GT voxels of "
            "Occ3D classes no prompt covers are ignored, mIoU over its classes, and known / unknown subsets "
            "from its @known line"),
    ) -> None:
        """Occ3D mIoU (mask_camera voxels, confusion matrix over the whole split) of predictions vs GT."""
        from ago_runtime.atomic import write_json, write_text
        from ago_runtime.scoring.metric import OccupancyMetric
        from ago_runtime.formats.occ3d import Occ3DLabels
        from ago_runtime.progress import track

        from ago_runtime.outputs import check_output_file

        space = None
        if prompts is not None:
            from ago_runtime.vocab.prompts import parse_prompt_file

            space = parse_prompt_file(prompts)
            K = space.num_classes
            m = OccupancyMetric(list(space.class_names) + ["free"], free_index=K)
            gt_lut = space.gt_lut(free_index=K)
            subsets = parse_subsets(subset, m.class_names)
            if space.known and any(c not in space.known for c in space.class_names):
                subsets.setdefault("known", [c for c in space.class_names if c in space.known])
                subsets.setdefault("unknown", [c for c in space.class_names if c not in space.known])
        else:
            m = OccupancyMetric()
            subsets = parse_subsets(subset, m.class_names)
        for option, target in (("--json", json_out), ("--md", md_out)):
            if target is not None:
                check_output_file(target, option)   # before scoring, not after the table
        if not pred.is_dir():
            raise AgoInputError(pred, "prediction folder not found")
        gts = find_gt_files(gt)
        pairs, missing = [], []
        for token, gt_file in gts.items():
            p = find_prediction(pred, gt_file)
            if p is None:
                missing.append(token)
            else:
                pairs.append((gt_file, p))
        if missing and not allow_missing:
            raise AgoInputError(pred, f"no prediction for {len(missing)} of {len(gts)} GT frames "
                                      f"(first: {missing[0]}); use --allow-missing to skip them")
        if not pairs:
            raise AgoInputError(pred, "no prediction matches any GT frame")
        for gt_file, p in track(pairs, description="scoring", total=len(pairs)):
            labels = Occ3DLabels.load(gt_file)
            sem, _ = load_semantics(p)
            gt_sem = labels.semantics
            if space is not None:
                sem = prediction_in_space(p, sem, m.class_names)
                gt_sem = gt_lut[gt_sem]
            sem = to_gt_resolution(sem, labels.shape, p)
            if sem.max() >= m.num_labels:
                raise AgoInputError(p, f"prediction labels must lie in 0..{m.num_labels - 1}, found {sem.max()}")
            m.update(sem, gt_sem, None if no_mask else labels.mask_camera.astype(bool))
        table = m.to_markdown(subsets)
        typer.echo(table)
        if missing:
            typer.echo(f"skipped {len(missing)} GT frame(s) with no prediction", err=True)
        if json_out is not None:
            summary = m.summary()
            summary["subsets"] = {name: {"classes": cls, "mIoU": _pct(m.miou(cls))}
                                  for name, cls in subsets.items()}
            summary["skipped_frames"] = missing
            write_json(json_out, summary)
        if md_out is not None:
            write_text(md_out, table)
