"""`open_dataset(root, ...)`: the dataset reader a folder's layout calls for.

- a `v1.0-*` table folder -> `NuScenesDataset` (real nuScenes or `ago synth --layout nuscenes`);
- a `cam_infos.json` -> `Occ3DWaymoDataset` (`ago synth --rig waymo|front`);
- anything else: one AgoInputError naming the folder and both layouts.

Both readers give `Frame`s and the same interface (len, [i], sample_tokens, scene_of, split, ...), and
`class_table`: the class table their ground truth's ids belong to: the layout's (Occ3D-nuScenes, Occ3D-Waymo), or
the folder's own `class_table.json` when it has one (`classes.dataset_class_table`). `check_label_table(ds, space, option)`
refuses a label space of another table (a nuScenes prompt file on Occ3D-Waymo data, or the reverse).
"""

from __future__ import annotations

from pathlib import Path

from ago_runtime.errors import AgoInputError

LAYOUTS = "a nuScenes layout (a v1.0-* table folder) or the Occ3D-Waymo layout (cam_infos.json)"


def dataset_layout(root: str | Path) -> str | None:
    """"nuscenes", "occ3d-waymo" or None, from what `root` holds (a v1.0-* folder wins)."""
    root = Path(root)
    if not root.is_dir():
        return None
    if any(p.is_dir() and p.name.startswith("v1.0-") for p in root.iterdir()):
        return "nuscenes"
    from ago_runtime.formats.occ3d_waymo_dataset import is_occ3d_waymo_root

    return "occ3d-waymo" if is_occ3d_waymo_root(root) else None


def open_dataset(root: str | Path, gts_root: str | Path | None = None, load_images: bool = True,
                 load_extras: bool = True, allow_outside_root: bool = False, **nuscenes_options):
    """The reader of the dataset at `root` (see the module docstring); `nuscenes_options` (version,
    num_sweeps, grid, compensate_ego_motion) go to NuScenesDataset (num_sweeps and grid also to the Waymo one)."""
    root = Path(root)
    if not root.is_dir():
        raise AgoInputError(root, "dataset folder not found")
    layout = dataset_layout(root)
    if layout == "nuscenes":
        from ago_runtime.formats.nuscenes import NuScenesDataset

        return NuScenesDataset(root, gts_root=gts_root, load_images=load_images, load_extras=load_extras,
                               allow_outside_root=allow_outside_root, **nuscenes_options)
    if layout == "occ3d-waymo":
        from ago_runtime.formats.occ3d_waymo_dataset import Occ3DWaymoDataset

        unknown = sorted(set(nuscenes_options) - {"num_sweeps", "grid"})
        if unknown:
            raise AgoInputError(root, f"the Occ3D-Waymo layout takes no {', '.join(unknown)}")
        return Occ3DWaymoDataset(root, gts_root=gts_root, load_images=load_images, load_extras=load_extras,
                                 allow_outside_root=allow_outside_root, **nuscenes_options)
    raise AgoInputError(root, f"not a dataset root: expected {LAYOUTS}")


def gt_folder_class_table(gt_root: str | Path):
    """The class table a ground-truth folder declares: `class_table.json` in it or in the dataset folder holding it
    (`<root>/gts`), else None (the files' layout says: Occ3D-nuScenes or Occ3D-Waymo)."""
    from ago_runtime.classes import dataset_class_table

    for folder in (Path(gt_root), Path(gt_root).parent):
        table = dataset_class_table(folder, None)
        if table is not None:
            return table
    return None


def check_label_table(ds, space, option: str = "--prompts") -> None:
    """AgoInputError naming `option` unless the label space `space` (a LabelSpace) indexes the class table
    of the dataset `ds`'s ground truth and synthetic maps."""
    from ago_runtime.classes import TABLE_FILE, shipped_name

    if space.class_table != ds.class_table:
        have = ds.class_table
        use = shipped_name(have) or f"<the path of {Path(ds.root) / TABLE_FILE}>"
        same_name = " (a table of the same name but other content)" if have.name == space.table else ""
        raise AgoInputError(option, f"the prompt file's classes are {space.table} ones (@table){same_name} but "
                            f"{ds.root} holds {have.name} labels: use a prompt file with '@table: {use}'")
