"""Calibration frames for static int8 quantisation: real frames, preprocessed the way the runtime preprocesses them.

Takes a folder the user names (`--calibration-data DIR`): a nuScenes-layout dataroot (e.g. a town written
by `ago synth`; its keyframes, optionally one split), a folder with an mmdet3d_info.pkl, or an images folder
(CAM_*.jpg + calib.json, one frame). Gives at most `max_frames` frames spread evenly over the folder's
frames, each as the planes graph's feed {"images": (1, V, 3, H, W) float32, "ego2img": (1, V, 4, 4) float32}
(ago_runtime.geometry.preprocess.Preprocess, as the export's parity frame).

Every problem with the folder is an AgoInputError naming `--calibration-data` (the CLI prints one line).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.camera import Rig
from ago_runtime.geometry.preprocess import Preprocess
from ago_runtime.predict.contract import PLANES_INPUTS

OPTION = "--calibration-data"
MAX_CALIBRATION_FRAMES = 64   # the most frames a calibration reads (each is one run of the planes graph)
CALIBRATION_FRAMES = 16       # what `ago export --int8` reads (5 and 25 frames gave the same labels:
                              # benchmarks/results/int8_static.md, sweep)


def spread(count: int, max_frames: int) -> list[int]:
    """max_frames indices spread evenly over range(count) (all of them when count <= max_frames)."""
    if count <= max_frames:
        return list(range(count))
    return [int(i) for i in np.linspace(0, count - 1, max_frames).round()]


def read_frames(source: str | Path, max_frames: int, fallback_rig: Rig | None = None,
                split: str | None = None) -> list[tuple[dict[str, np.ndarray], Rig, str]]:
    """-> [(images by camera, rig, name)] of at most max_frames frames of `source` (see the module doc)."""
    if not 1 <= max_frames <= MAX_CALIBRATION_FRAMES:
        raise AgoInputError(OPTION, f"the number of calibration frames must be 1..{MAX_CALIBRATION_FRAMES}, "
                            f"got {max_frames}")
    source = Path(source)
    if not source.is_dir():
        raise AgoInputError(OPTION, f"{source}: folder not found (a nuScenes dataroot such as `ago synth` "
                            "writes, a folder with mmdet3d_info.pkl, or an images folder)")
    try:
        from ago_runtime.formats.datasets import dataset_layout, open_dataset

        if dataset_layout(source) is not None:   # a nuScenes dataroot or an Occ3D-Waymo layout
            ds = open_dataset(source, load_extras=False)
            indices = ds.split(split) if split else list(range(len(ds)))
            if not indices:
                raise AgoInputError(OPTION, f"{source}: no keyframes" + (f" in split {split!r}" if split else ""))
            frames = [ds[indices[i]] for i in spread(len(indices), max_frames)]
            return [(f.images, f.rig, f"{source} (sample {f.token})") for f in frames]
        if split:
            raise AgoInputError(OPTION, f"{source}: a split ({split!r}) needs a dataset (nuScenes or Occ3D-Waymo layout)")
        if (source / "mmdet3d_info.pkl").is_file():
            from ago_runtime.formats.mmdet3d_info import load_mmdet3d_info

            infos = load_mmdet3d_info(source / "mmdet3d_info.pkl", source)
            if not infos:
                raise AgoInputError(OPTION, f"{source / 'mmdet3d_info.pkl'}: no frames")
            frames = [infos[i] for i in spread(len(infos), max_frames)]
            return [(f.images, f.rig, f"{source} (sample {f.token})") for f in frames]
        from ago_runtime.formats.calibration import load_images_folder

        images, rig, _ = load_images_folder(source, fallback_rig=fallback_rig)
        return [(images, rig, str(source))]
    except AgoInputError as e:
        if e.path == OPTION:
            raise
        raise AgoInputError(OPTION, str(e)) from None


def planes_feeds(frames: list[tuple[dict[str, np.ndarray], Rig, str]], pre: Preprocess) -> list[dict[str, np.ndarray]]:
    """Frames -> the planes graph's feeds (images (1, V, 3, H, W), ego2img (1, V, 4, 4), float32)."""
    if not frames:
        raise AgoInputError(OPTION, "no calibration frames")
    feeds = []
    for images, rig, name in frames:
        try:
            feeds.append(dict(zip(PLANES_INPUTS, (pre.images(images, rig, name)[None], pre.ego2img(rig)[None]))))
        except AgoInputError as e:
            raise AgoInputError(OPTION, str(e)) from None
    return feeds
