"""CLI verb `ago show`: pictures of occupancy grids and camera rigs.

`ago show LABELS.npz [--gt GT.npz] [--view bev|voxels|both] [--classes TABLE] [--out out.png]`
    PNG of an occupancy grid (any npz with a `semantics` (X, Y, Z) array, or an Occ3D-Waymo
    ground-truth file, drawn with the Occ3D-Waymo class table); with --gt, prediction and ground
    truth side by side (voxels outside the GT's mask_camera washed out). --classes: a class table
    (occ3d_nuscenes, occ3d_waymo or a JSON file, see ago_runtime/classes.py) for the labels' ids.
`ago show DATASET_DIR (--sample TOKEN | --index I) [--out out.png]`
    the camera images of one dataset sample (nuScenes or Occ3D-Waymo layout), with its ground truth as a BEV.
`--html OUT.html` (either form): the interactive 3-D page of ago_runtime/pictures/html_viewer.py instead of (or,
    with --out, beside) the PNG; with --gt (a labels.npz, or a GT folder holding <token>/labels.npz) the ground
    truth beside the prediction with one camera; a dataset sample's page shows its ground truth and its images.
(`ago metric`, which scores such grids, is in ago_runtime/scoring/cli.py.)
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from ago_runtime.classes import FREE, OCC3D_CLASSES, OCC3D_COLORS, ClassTable, load_class_table
from ago_runtime.errors import AgoInputError, refuse_unused
from ago_runtime.formats.occ3d import load_semantics
from ago_runtime.formats.occ3d_waymo import is_waymo_file, load_ground_truth
from ago_runtime.scoring.metric import to_gt_resolution


class View(str, Enum):
    """`ago show --view`."""

    BEV = "bev"
    VOXELS = "voxels"
    BOTH = "both"


def register(app: typer.Typer) -> None:
    @app.command("show")
    def show(
        path: Path = typer.Argument(..., help="labels.npz (key 'semantics'), or a dataset folder (nuScenes or Occ3D-Waymo layout)"),
        out: Optional[Path] = typer.Option(None, "--out", "-o", help="PNG to write (default: ago_show.png, none "
                                           "with --html)"),
        gt: Optional[Path] = typer.Option(None, "--gt", help="ground-truth labels.npz: draw prediction vs GT (with "
                                          "--html also a GT folder holding <token>/labels.npz)"),
        html: Optional[Path] = typer.Option(None, "--html", help="also write an interactive 3-D page (one "
                                            "self-contained .html file, no network needed)"),
        view: Optional[View] = typer.Option(None, "--view", help="what the PNG draws (default both; a grid only)"),
        sample: Optional[str] = typer.Option(None, "--sample", help="dataset folder: sample token"),
        index: Optional[int] = typer.Option(None, "--index", help="dataset folder: sample index"),
        use_mask: Optional[bool] = typer.Option(None, "--mask/--no-mask",
                                                help="wash out voxels outside mask_camera (default: on with --gt)"),
        classes: Optional[str] = typer.Option(None, "--classes",
                                              help="class table of the labels: occ3d_nuscenes, occ3d_waymo or a JSON "
                                                   "file (default: occ3d_waymo for Occ3D-Waymo files, else occ3d_nuscenes)"),
    ) -> None:
        """Draw an occupancy grid (BEV and/or 3-D voxels) or a sample's six camera images as a PNG."""
        from ago_runtime.pictures import render

        from ago_runtime.outputs import check_output_file, check_suffix

        if not path.exists():
            raise AgoInputError(path, "not found (give a labels .npz or a dataset folder)")
        if path.is_dir():
            refuse_unused({"--gt": gt, "--view": view, "--mask/--no-mask": use_mask, "--classes": classes},
                          f"a dataset folder ({path}); it draws a sample's cameras")
        else:
            refuse_unused({"--sample": sample, "--index": index}, f"a labels file ({path.name}); they pick a "
                          "sample of a dataset folder")
        view = (view or View.BOTH).value
        if html is not None:
            from ago_runtime.pictures.html_viewer import HTML_SUFFIXES

            check_output_file(html, "--html")
            check_suffix(html, HTML_SUFFIXES, "--html")
        if out is None and html is None:
            out = Path("ago_show.png")
        if out is not None:
            check_output_file(out, "--out")
            check_suffix(out, (".png",), "--out")   # the picture is a PNG
        table = load_class_table(classes) if classes is not None else None
        if html is not None:
            _write_page(html, path, gt, table, sample, index)
            typer.echo(f"wrote {html}")
        if out is None:
            return
        if path.is_dir():
            image = _rig_picture(path, sample, index)
        else:
            sem, mask, file_table = _load_grid(path)
            table = table or file_table
            if gt is not None:
                gt_sem, gt_mask, gt_table = _load_grid(gt)
                table = table or gt_table
                if sem.shape != gt_sem.shape:
                    sem = to_gt_resolution(sem, gt_sem.shape, path)
                image = render.prediction_vs_gt(sem, gt_sem, gt_mask if use_mask is not False else None, views=view,
                                                titles=(path.parent.name + "/" + path.name, "ground truth"),
                                                table=table)
            else:
                m = mask if use_mask else None  # a single grid is drawn whole unless --mask
                panels = []
                if view in ("bev", "both"):
                    panels.append(("BEV (x forward = up)", render.bev_image(sem, mask=m, scale=4, table=table)))
                if view in ("voxels", "both"):
                    panels.append(("3-D", render.voxel_view(sem, mask=m, table=table)))
                fig = render.side_by_side(panels)
                if table is None:
                    present = [i for i in np.unique(sem).tolist() if i < FREE]
                    names, colors = [OCC3D_CLASSES[i] for i in present], OCC3D_COLORS[present]
                else:
                    present = [i for i in np.unique(sem).tolist() if i in table.ids]
                    names, colors = [table.name_of(i) for i in present], table.palette_by_id()[present]
                image = render.stack_vertical([fig, render.legend(names, colors, width=fig.shape[1])])
        render.save_png(out, image)
        typer.echo(f"wrote {out} ({image.shape[1]}x{image.shape[0]})")

def _write_page(html: Path, path: Path, gt: Path | None, table: ClassTable | None, sample: str | None,
               index: int | None) -> None:
    """`ago show ... --html`: a grid file's page (with --gt, the ground truth beside it), or a dataset sample's
    ground truth with its camera images."""
    from ago_runtime.pictures.html_viewer import view_from_arrays, write_viewer

    if path.is_dir():
        frame, ds_table = _sample_frame(path, sample, index)
        if frame.gt is None:
            raise AgoInputError(path, f"sample {frame.token} has no ground truth to draw in 3-D")
        view = view_from_arrays({"semantics": frame.gt.semantics}, path, "ground truth", table=table or ds_table)
        write_viewer(html, [view], frame.images, f"{frame.scene}  sample {frame.token}", source=str(path))
        return
    arrays, source, file_table = _grid_arrays(path)
    views = [view_from_arrays(arrays, source, "prediction" if gt else path.name, table=table or file_table)]
    if gt is not None:
        gt_file = _gt_file_for(gt, path)
        gt_arrays, gt_source, gt_table = _grid_arrays(gt_file)
        views.append(view_from_arrays(gt_arrays, gt_source, "ground truth", table=table or gt_table))
        if views[1].semantics.shape != views[0].semantics.shape:
            raise AgoInputError(gt_file, f"shape {views[1].semantics.shape} differs from the prediction's "
                                         f"{views[0].semantics.shape}")
    write_viewer(html, views, None, str(path), source=str(path))


VIEW_KEYS = ("semantics", "class_names", "free_index", "class_table", "class_colors", "entropy", "unexplained",
             "unexplained_threshold", "similarity")


def _grid_arrays(path: Path) -> tuple[dict, Path, ClassTable | None]:
    """(the arrays the 3-D page draws, the path, the class table the file implies or None) of a grid file: an
    Occ3D-Waymo ground-truth file comes with OCC3D_WAYMO (its labels in file ids); any other npz needs 'semantics'."""
    from ago_runtime.readers import read_npz

    if path.is_file() and is_waymo_file(path):
        labels, table = load_ground_truth(path)
        return {"semantics": labels.semantics}, path, table
    load_semantics(path)   # a readable npz with a 3-D 'semantics', else one error naming the file
    with np.load(path, allow_pickle=False) as z:
        keys = [k for k in VIEW_KEYS if k in z.files]
    return read_npz(path, keys, "prediction file"), path, None


def _gt_file_for(gt: Path, pred: Path) -> Path:
    """--gt: a labels file, or a GT folder searched for the prediction's sample token (`<token>.npz`, or
    `<token>/labels.npz`: the token is the file's stem or its folder's name)."""
    from ago_runtime.scoring.cli import find_gt_files

    if not gt.is_dir():
        return gt
    token = pred.parent.name if pred.name == "labels.npz" else pred.stem
    found = find_gt_files(gt)
    if token not in found:
        raise AgoInputError(gt, f"no ground truth for sample {token!r} ({len(found)} labels files searched)")
    return found[token][1]


def _load_grid(path: Path) -> tuple[np.ndarray, np.ndarray | None, ClassTable | None]:
    """(semantics, mask_camera or None, class table or None = today's Occ3D-nuScenes default) of a grid file:
    an Occ3D-Waymo ground-truth file (key voxel_label) comes with OCC3D_WAYMO."""
    if path.is_file() and is_waymo_file(path):
        labels, table = load_ground_truth(path)
        return labels.semantics, labels.mask_camera.astype(bool), table
    sem, mask = load_semantics(path)
    return sem, mask, prediction_table(path)


def prediction_table(path: Path) -> ClassTable | None:
    """The class table of an `ago infer` file written in another table than Occ3D-nuScenes (keys class_table,
    class_names, class_colors: its dense order, free last; html_viewer.recorded_table), else None."""
    from ago_runtime.pictures.html_viewer import recorded_table

    from ago_runtime.readers import open_npz

    if not path.is_file():
        return None
    with open_npz(path, "prediction file") as z:
        arrays = {k: z[k] for k in ("class_table", "class_names", "class_colors") if k in z.files}
    return recorded_table(arrays, path)


def _rig_picture(root: Path, sample: str | None, index: int | None) -> np.ndarray:
    """The camera images of one sample of a dataset (nuScenes or Occ3D-Waymo layout) in `render.rig_mosaic`'s
    layout, with the sample's GT as a BEV (in the dataset's class table) beside it when there is one."""
    from ago_runtime.pictures import render

    frame, table = _sample_frame(root, sample, index)
    rig = render.rig_mosaic(frame.images)
    title = f"{frame.scene}  sample {frame.token}"
    if frame.gt is None:
        return render.side_by_side([(title, rig)])
    scale = max(1, int(round(rig.shape[0] / frame.gt.shape[0])))
    bev = render.bev_image(frame.gt.semantics, scale=scale, mask=frame.gt.mask_camera, table=table)
    return render.side_by_side([(title, rig), ("Occ3D GT (BEV, forward = up)", bev)])


def _sample_frame(root: Path, sample: str | None, index: int | None):
    """(the Frame of one sample of a dataset folder, the dataset's class table): --sample TOKEN or --index I."""
    from ago_runtime.formats.datasets import open_dataset

    if (sample is None) == (index is None):
        raise AgoInputError(root, "a dataset folder needs exactly one of --sample TOKEN or --index I")
    ds = open_dataset(root, load_extras=False)
    if index is None:
        index = ds.index_of(sample)
    if not 0 <= index < len(ds):
        raise AgoInputError(root, f"--index {index} out of range (the dataset has {len(ds)} samples)")
    return ds[index], ds.class_table
