"""CLI verbs `ago show` (pictures of occupancy grids / camera rigs) and `ago metric` (Occ3D mIoU).

`ago show LABELS.npz [--gt GT.npz] [--view bev|voxels|both] [--out out.png]`
    PNG of an occupancy grid (any npz with a `semantics` (X, Y, Z) array); with --gt, prediction
    and ground truth side by side (voxels outside the GT's mask_camera washed out).
`ago show DATASET_DIR (--sample TOKEN | --index I) [--out out.png]`
    the six camera images of one nuScenes-layout sample in the 2 x 3 rig layout.
`ago metric --pred DIR --gt DIR [--json out.json] [--md out.md] [--subset NAME=c1,c2]`
    evaluates predictions against Occ3D ground truth (see `ago_runtime.scoring.metric`).
    GT: `<gt>/<scene>/<token>/labels.npz` (searched recursively). Predictions, matched by sample
    token: `<pred>/<scene>/<token>/labels.npz`, `<pred>/<token>/labels.npz` or `<pred>/<token>.npz`,
    each with a `semantics` array at GT resolution or an integer fraction of it (upsampled by
    nearest-neighbour repetition; evaluation is at GT resolution).
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import List, Optional

import numpy as np
import typer

from ago_runtime.classes import FREE, OCC3D_CLASSES, OCC3D_COLORS
from ago_runtime.errors import AgoInputError


# ---------------------------------------------------------------------------------------- loading
def load_semantics(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read `semantics` (X, Y, Z) uint8 and, when present, `mask_camera` (as bool) from an npz.

    Raises AgoInputError naming the file for anything unreadable or malformed.
    """
    path = Path(path)
    if not path.is_file():
        raise AgoInputError(path, "file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "semantics" not in z.files:
                raise AgoInputError(path, f"no 'semantics' array (found {sorted(z.files)})")
            sem = np.asarray(z["semantics"])
            mask = np.asarray(z["mask_camera"]) if "mask_camera" in z.files else None
    except AgoInputError:
        raise
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise AgoInputError(path, f"not a readable npz file ({e.__class__.__name__}: {e})") from None
    if sem.ndim != 3:
        raise AgoInputError(path, f"'semantics' must be a 3-D (X, Y, Z) array, got shape {sem.shape}")
    if not np.issubdtype(sem.dtype, np.integer):
        raise AgoInputError(path, f"'semantics' must hold integer labels, got dtype {sem.dtype}")
    if sem.size and (sem.min() < 0 or sem.max() > 255):
        raise AgoInputError(path, f"'semantics' labels must lie in 0..255, found {sem.min()}..{sem.max()}")
    if mask is not None and mask.shape != sem.shape:
        raise AgoInputError(path, f"'mask_camera' shape {mask.shape} != 'semantics' shape {sem.shape}")
    return sem.astype(np.uint8), (None if mask is None else mask.astype(bool))


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


def to_gt_resolution(pred: np.ndarray, gt_shape: tuple[int, ...], path: Path) -> np.ndarray:
    """Upsample a coarser prediction by an integer factor per axis; refuse any other shape."""
    from ago_runtime.scoring.metric import upsample_nearest

    if pred.shape == tuple(gt_shape):
        return pred
    factors = [g // p if p and g % p == 0 else 0 for g, p in zip(gt_shape, pred.shape)]
    if 0 in factors:
        raise AgoInputError(path, f"prediction shape {pred.shape} is not the GT shape {tuple(gt_shape)} "
                                  "nor an integer fraction of it")
    return upsample_nearest(pred, factors)


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


# ---------------------------------------------------------------------------------------- verbs
def register(app: typer.Typer) -> None:
    @app.command("show")
    def show(
        path: Path = typer.Argument(..., help="labels.npz (key 'semantics'), or a nuScenes-layout dataset folder"),
        out: Path = typer.Option(Path("ago_show.png"), "--out", "-o", help="PNG to write"),
        gt: Optional[Path] = typer.Option(None, "--gt", help="ground-truth labels.npz: draw prediction vs GT"),
        view: str = typer.Option("both", "--view", help="bev | voxels | both"),
        sample: Optional[str] = typer.Option(None, "--sample", help="dataset folder: sample token"),
        index: Optional[int] = typer.Option(None, "--index", help="dataset folder: sample index"),
        use_mask: Optional[bool] = typer.Option(None, "--mask/--no-mask",
                                                help="wash out voxels outside mask_camera (default: on with --gt)"),
    ) -> None:
        """Draw an occupancy grid (BEV and/or 3-D voxels) or a sample's six camera images as a PNG."""
        from ago_runtime.pictures import render

        from ago_runtime.outputs import check_output_file

        if view not in ("bev", "voxels", "both"):
            raise AgoInputError("--view", f"must be bev, voxels or both, got {view!r}")
        if not path.exists():
            raise AgoInputError(path, "not found (give a labels .npz or a dataset folder)")
        check_output_file(out, "--out")
        if path.is_dir():
            image = _rig_picture(path, sample, index)
        else:
            sem, mask = load_semantics(path)
            if gt is not None:
                gt_sem, gt_mask = load_semantics(gt)
                if sem.shape != gt_sem.shape:
                    sem = to_gt_resolution(sem, gt_sem.shape, path)
                image = render.prediction_vs_gt(sem, gt_sem, gt_mask if use_mask is not False else None, views=view,
                                                titles=(path.parent.name + "/" + path.name, "ground truth"))
            else:
                m = mask if use_mask else None  # a single grid is drawn whole unless --mask
                panels = []
                if view in ("bev", "both"):
                    panels.append(("BEV (x forward = up)", render.bev_image(sem, mask=m, scale=4)))
                if view in ("voxels", "both"):
                    panels.append(("3-D", render.voxel_view(sem, mask=m)))
                fig = render.side_by_side(panels)
                present = [i for i in np.unique(sem).tolist() if i < FREE]
                names = [OCC3D_CLASSES[i] for i in present]
                image = render.stack_vertical([fig, render.legend(names, OCC3D_COLORS[present], width=fig.shape[1])])
        render.save_png(out, image)
        typer.echo(f"wrote {out} ({image.shape[1]}x{image.shape[0]})")

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
            summary["subsets"] = {name: {"classes": cls, "mIoU": _pct_or_none(m.miou(cls))}
                                  for name, cls in subsets.items()}
            summary["skipped_frames"] = missing
            write_json(json_out, summary)
        if md_out is not None:
            write_text(md_out, table)


def _pct_or_none(x: float) -> float | None:
    return None if not np.isfinite(x) else round(float(x) * 100, 2)


def _rig_picture(root: Path, sample: str | None, index: int | None) -> np.ndarray:
    """The six camera images of one sample of a nuScenes-layout dataset in the 2 x 3 rig layout,
    with the sample's Occ3D GT as a BEV beside it when the dataset has one."""
    from ago_runtime.pictures import render
    from ago_runtime.formats.nuscenes import NuScenesDataset

    if (sample is None) == (index is None):
        raise AgoInputError(root, "a dataset folder needs exactly one of --sample TOKEN or --index I")
    ds = NuScenesDataset(root, load_extras=False)
    if index is None:
        index = ds.index_of(sample)
    if not 0 <= index < len(ds):
        raise AgoInputError(root, f"--index {index} out of range (the dataset has {len(ds)} samples)")
    frame = ds[index]
    rig = render.rig_mosaic(frame.images)
    title = f"{frame.scene}  sample {frame.token}"
    if frame.gt is None:
        return render.side_by_side([(title, rig)])
    scale = max(1, int(round(rig.shape[0] / frame.gt.shape[0])))
    bev = render.bev_image(frame.gt.semantics, scale=scale, mask=frame.gt.mask_camera)
    return render.side_by_side([(title, rig), ("Occ3D GT (BEV, forward = up)", bev)])
