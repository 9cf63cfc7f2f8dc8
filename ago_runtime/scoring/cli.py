"""CLI verb `ago metric`: the Occ3D mIoU of predictions against ground truth.

`ago metric --pred DIR --gt DIR [--json out.json] [--md out.md] [--subset NAME=c1,c2]`
    evaluates predictions against Occ3D ground truth (see `ago_runtime.scoring.metric`).
    GT: `<gt>/<scene>/<token>/labels.npz` (searched recursively). Predictions, matched by sample
    token: `<pred>/<scene>/<token>/labels.npz`, `<pred>/<token>/labels.npz` or `<pred>/<token>.npz`,
    each with a `semantics` array at GT resolution or an integer fraction of it (upsampled by
    nearest-neighbour repetition; evaluation is at GT resolution).
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

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
    ) -> None:
        """Occ3D mIoU (mask_camera voxels, confusion matrix over the whole split) of predictions vs GT."""
        from ago_runtime.atomic import write_json, write_text
        from ago_runtime.scoring.metric import OccupancyMetric
        from ago_runtime.formats.occ3d import Occ3DLabels
        from ago_runtime.progress import track

        from ago_runtime.outputs import check_output_file

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
            sem = to_gt_resolution(sem, labels.shape, p)
            if sem.max() >= m.num_labels:
                raise AgoInputError(p, f"prediction labels must lie in 0..{m.num_labels - 1}, found {sem.max()}")
            m.update(sem, labels.semantics, None if no_mask else labels.mask_camera.astype(bool))
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
