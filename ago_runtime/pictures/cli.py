"""CLI verb `ago show`: pictures of occupancy grids and camera rigs.

`ago show LABELS.npz [--gt GT.npz] [--view bev|voxels|both] [--classes TABLE] [--out out.png]`
    PNG of an occupancy grid (any npz with a `semantics` (X, Y, Z) array, or an Occ3D-Waymo
    ground-truth file, drawn with the Occ3D-Waymo class table); with --gt, prediction and ground
    truth side by side (voxels outside the GT's mask_camera washed out). --classes: a class table
    (occ3d_nuscenes, occ3d_waymo or a JSON file, see ago_runtime/classes.py) for the labels' ids.
`ago show DATASET_DIR (--sample TOKEN | --index I) [--out out.png]`
    the camera images of one dataset sample (nuScenes or Occ3D-Waymo layout), with its ground truth as a BEV.
(`ago metric`, which scores such grids, is in ago_runtime/scoring/cli.py.)
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import typer

from ago_runtime.classes import FREE, OCC3D_CLASSES, OCC3D_COLORS, ClassTable, load_class_table
from ago_runtime.errors import AgoInputError, refuse_unused
from ago_runtime.formats.occ3d import load_semantics
from ago_runtime.formats.occ3d_waymo import is_waymo_file, load_ground_truth
from ago_runtime.scoring.metric import to_gt_resolution


def register(app: typer.Typer) -> None:
    @app.command("show")
    def show(
        path: Path = typer.Argument(..., help="labels.npz (key 'semantics'), or a dataset folder (nuScenes or Occ3D-Waymo layout)"),
        out: Path = typer.Option(Path("ago_show.png"), "--out", "-o", help="PNG to write"),
        gt: Optional[Path] = typer.Option(None, "--gt", help="ground-truth labels.npz: draw prediction vs GT"),
        view: Optional[str] = typer.Option(None, "--view", help="bev | voxels | both (default both; a grid only)"),
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

        if view is not None and view not in ("bev", "voxels", "both"):
            raise AgoInputError("--view", f"must be bev, voxels or both, got {view!r}")
        if not path.exists():
            raise AgoInputError(path, "not found (give a labels .npz or a dataset folder)")
        if path.is_dir():
            refuse_unused({"--gt": gt, "--view": view, "--mask/--no-mask": use_mask, "--classes": classes},
                          f"a dataset folder ({path}); it draws a sample's cameras")
        else:
            refuse_unused({"--sample": sample, "--index": index}, f"a labels file ({path.name}); they pick a "
                          "sample of a dataset folder")
        view = view or "both"
        check_output_file(out, "--out")
        check_suffix(out, (".png",), "--out")   # the picture is a PNG
        table = load_class_table(classes) if classes is not None else None
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
    class_names, class_colors: its dense order, free last), else None."""
    from ago_runtime.errors import AgoInputError

    from ago_runtime.readers import open_npz

    if not path.is_file():
        return None
    with open_npz(path, "prediction file") as z:
        if not {"class_table", "class_names", "class_colors"} <= set(z.files):
            return None
        name, names, colors = str(z["class_table"]), [str(c) for c in z["class_names"]], z["class_colors"]
    if names[-1:] != ["free"] or colors.shape != (len(names), 3):
        raise AgoInputError(path, "class_names must end with 'free' and class_colors give one RGB per name")
    try:
        return ClassTable(name, tuple(names[:-1]), tuple(range(len(names) - 1)), len(names) - 1,
                          tuple(tuple(int(c) for c in row) for row in colors))
    except ValueError as e:
        raise AgoInputError(path, str(e)) from None


def _rig_picture(root: Path, sample: str | None, index: int | None) -> np.ndarray:
    """The camera images of one sample of a dataset (nuScenes or Occ3D-Waymo layout) in `render.rig_mosaic`'s
    layout, with the sample's GT as a BEV (in the dataset's class table) beside it when there is one."""
    from ago_runtime.pictures import render
    from ago_runtime.formats.datasets import open_dataset

    if (sample is None) == (index is None):
        raise AgoInputError(root, "a dataset folder needs exactly one of --sample TOKEN or --index I")
    ds = open_dataset(root, load_extras=False)
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
    bev = render.bev_image(frame.gt.semantics, scale=scale, mask=frame.gt.mask_camera, table=ds.class_table)
    return render.side_by_side([(title, rig), ("Occ3D GT (BEV, forward = up)", bev)])
