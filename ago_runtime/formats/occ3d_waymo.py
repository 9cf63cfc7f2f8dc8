"""Occ3D-Waymo ground-truth files, as the dataset ships them (docs/dataset_format.md, "Occ3D-Waymo").

Layout: `<root>/<split>/<scene>/<frame>_04.npz` (0.4 m grid, 200 x 200 x 16) and `<frame>.npz`
(0.1 m grid, 1600 x 1600 x 64); split = training | validation | test, scene and frame three digits.
Keys: `voxel_label` (class ids 0..14, free 23: `ago_runtime.classes.OCC3D_WAYMO`),
`origin_voxel_state` (LiDAR mask), `final_voxel_state` (camera mask), `infov` (inside the five
cameras' field of view); every array (X, Y, Z), masks 0/1.

`Occ3DWaymoLabels.load(path)` reads one file without unpickling (sizes checked before reading) and
refuses, in one AgoInputError naming the file, a missing key, unequal or non-3-D shapes, non-integer
labels, a label the class table does not name, or a mask holding anything but 0/1.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ago_runtime.atomic import save_npz
from ago_runtime.classes import OCC3D_WAYMO, ClassTable
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.occ3d import Occ3DLabels, read_voxel_arrays

KEYS = ("voxel_label", "origin_voxel_state", "final_voxel_state", "infov")
SPLITS = ("training", "validation", "test")
VOXEL_SUFFIX = {"0.4": "_04", "0.1": ""}     # voxel size -> file-name suffix
GRID_SHAPE = {"0.4": (200, 200, 16), "0.1": (1600, 1600, 64)}
_FILE = {"0.4": re.compile(r"^(\d{3})_04\.npz$"), "0.1": re.compile(r"^(\d{3})\.npz$")}
_SCENE = re.compile(r"^\d{3}$")


@dataclass
class Occ3DWaymoLabels:
    semantics: np.ndarray    # (X, Y, Z) uint8, the table's ids (free = 23)
    mask_lidar: np.ndarray   # (X, Y, Z) uint8 0/1  (origin_voxel_state)
    mask_camera: np.ndarray  # (X, Y, Z) uint8 0/1  (final_voxel_state)
    mask_fov: np.ndarray     # (X, Y, Z) uint8 0/1  (infov)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.semantics.shape)

    @classmethod
    def load(cls, path: str | Path, shape: tuple[int, int, int] | None = None,
             table: ClassTable = OCC3D_WAYMO) -> "Occ3DWaymoLabels":
        """Read and check one ground-truth npz; `shape`, when given, must match."""
        path = Path(path)
        arrays = read_voxel_arrays(path, KEYS, "Occ3D-Waymo ground-truth file", shape)
        sem = arrays["voxel_label"]
        if not np.issubdtype(sem.dtype, np.integer):
            raise AgoInputError(path, f"'voxel_label' must hold integer labels, got dtype {sem.dtype}")
        try:
            table.to_dense(sem, "'voxel_label' labels")
        except ValueError as e:
            raise AgoInputError(path, str(e)) from None
        for key in KEYS[1:]:
            a = arrays[key]
            if a.dtype != bool and not (np.issubdtype(a.dtype, np.integer) and (a.size == 0 or (a.min() >= 0 and a.max() <= 1))):
                raise AgoInputError(path, f"'{key}' must be a 0/1 mask, got dtype {a.dtype}"
                                    + (f" with values {a.min()}..{a.max()}" if np.issubdtype(a.dtype, np.number) and a.size else ""))
        return cls(sem.astype(np.uint8), *(arrays[k].astype(np.uint8) for k in KEYS[1:]))

    def as_occ3d(self) -> Occ3DLabels:
        """The labels as every consumer of a `Frame.gt` reads them: semantics = `voxel_label` (Waymo ids, free 23),
        mask_lidar = `origin_voxel_state`, mask_camera = `final_voxel_state & infov`: the mask Occ3D-Waymo's
        loaders train and score with (CVT-Occ's `LoadOccGTFromFileWaymo`, use_camera_mask and use_infov_mask on)."""
        return Occ3DLabels(self.semantics, self.mask_lidar, (self.mask_camera & self.mask_fov).astype(np.uint8))

    def save(self, path: str | Path) -> None:
        """Write the four arrays under Occ3D-Waymo's keys (uint8), atomically."""
        save_npz(path, voxel_label=self.semantics.astype(np.uint8),
                 origin_voxel_state=self.mask_lidar.astype(np.uint8),
                 final_voxel_state=self.mask_camera.astype(np.uint8), infov=self.mask_fov.astype(np.uint8))


def is_waymo_file(path: str | Path) -> bool:
    """True when an .npz holds Occ3D-Waymo's `voxel_label` key (reads the member list only; False if unreadable)."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as zf:
            return "voxel_label.npy" in zf.namelist()
    except (OSError, zipfile.BadZipFile):
        return False


def load_ground_truth(path: str | Path) -> tuple[Occ3DLabels, ClassTable]:
    """A ground-truth file of either layout -> (`Occ3DLabels`, the class table of its ids): an Occ3D-Waymo
    `_04.npz` (key `voxel_label`; ids kept, free 23, mask_camera = final_voxel_state & infov:
    `Occ3DWaymoLabels.as_occ3d`) or an Occ3D-nuScenes `labels.npz`."""
    from ago_runtime.classes import OCC3D_NUSCENES

    if is_waymo_file(path):
        return Occ3DWaymoLabels.load(path).as_occ3d(), OCC3D_WAYMO
    return Occ3DLabels.load(path), OCC3D_NUSCENES


def gt_path(root: str | Path, split: str, scene: int, frame: int, voxel_size: str = "0.4") -> Path:
    """`<root>/<split>/<scene:03d>/<frame:03d>_04.npz` (voxel_size "0.4") or `<frame:03d>.npz` ("0.1")."""
    if split not in SPLITS:
        raise AgoInputError(split, f"unknown Occ3D-Waymo split (one of {', '.join(SPLITS)})")
    if voxel_size not in VOXEL_SUFFIX:
        raise AgoInputError(voxel_size, "voxel size must be '0.4' or '0.1'")
    if not (0 <= int(scene) <= 999 and 0 <= int(frame) <= 999):
        raise AgoInputError(f"{scene}/{frame}", "scene and frame are numbers 0..999 (three digits in file names)")
    return Path(root) / split / f"{int(scene):03d}" / f"{int(frame):03d}{VOXEL_SUFFIX[voxel_size]}.npz"


def sample_of(split: str, scene: int, frame: int) -> str:
    """`<p><scene:03d><frame:03d>` (p = 0 training, 1 validation, 2 test): the mmdet3d KITTI-format sample name
    Occ3D-Waymo loaders parse (characters 1..3 the scene, 4..6 the frame)."""
    return f"{SPLITS.index(split)}{int(scene):03d}{int(frame):03d}"


def list_gt_files(root: str | Path, split: str, voxel_size: str = "0.4") -> list[tuple[int, int, Path]]:
    """(scene, frame, path) of every ground-truth file of one split, sorted; AgoInputError if the split folder is missing."""
    gt_path(root, split, 0, 0, voxel_size)   # checks split and voxel size
    folder = Path(root) / split
    if not folder.is_dir():
        raise AgoInputError(folder, "no such Occ3D-Waymo split folder")
    out = []
    for scene_dir in sorted(p for p in folder.iterdir() if p.is_dir() and _SCENE.match(p.name)):
        for f in sorted(scene_dir.iterdir()):
            m = _FILE[voxel_size].match(f.name)
            if m and f.is_file():
                out.append((int(scene_dir.name), int(m.group(1)), f))
    return out
