"""Frame sources for `Predictor.predict_many`: `open_frames(path)` -> the frames of an images folder, a
dataset root (nuScenes or Occ3D-Waymo layout) or an mmdetection3d info file, as `InputFrame`s.

    frames = open_frames("DATAROOT")                 # every keyframe; samples=["scene-0061", TOKEN] picks some
    len(frames)                                      # known before any image is decoded
    for frame in frames:                             # decoded one at a time, in order (one pass)
        frame.name, frame.images, frame.rig          # sample token (a folder: its name), camera -> RGB, calibration

Bad arguments (a missing folder, an unknown sample) raise `AgoInputError` in `open_frames`, before any
image is read. File names in the data files stay under the data root (ago_runtime.paths) unless
allow_outside_root.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, NamedTuple, Sequence

import numpy as np

from ago_runtime.errors import AgoInputError
from ago_runtime.geometry.camera import Rig

__all__ = ["InputFrame", "Frames", "open_frames"]


class InputFrame(NamedTuple):
    """One frame to predict: its name (the output's name), images (camera -> RGB uint8), rig, and what to
    name in errors (a folder or data file)."""

    name: str
    images: dict[str, np.ndarray]
    rig: Rig
    source: Any = None


class Frames:
    """The frames `open_frames` found: `len()` is known up front, iterating decodes them in order (once)."""

    def __init__(self, count: int, frames: Iterable[InputFrame]):
        self._count, self._frames = count, frames

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator[InputFrame]:
        return iter(self._frames)


def open_frames(path: str | Path | None, samples: str | Sequence[str] | None = None, info: str | Path | None = None,
                rig: Rig | None = None, *, skip: Callable[[str], bool] | None = None,
                allow_outside_root: bool = False, shard: tuple[int, int] | None = None) -> Frames:
    """The frames of `path`: an images folder (one frame; `rig` is the rig used when it has no calib.json),
    a dataset root (every keyframe, or those of `samples`: sample tokens and/or scene names, each scene
    giving its keyframes in time order), or with `info` (an mmdetection3d info .pkl) that file's frames,
    `path` (default: the pkl's folder) the data root.
    skip(name) True: a frame of a dataset or info file left out before its images are read (a resumed
    run); an images folder is never skipped. shard: (K, N), the K-th of N contiguous runs of a dataset's
    frames (ago_runtime.shards), taken before `skip` so that shards never change."""
    from ago_runtime.formats.calibration import find_camera_images, load_images_folder
    from ago_runtime.geometry.camera import CAMERA_NAMES
    from ago_runtime.shards import shard_indices

    wanted = [samples] if isinstance(samples, str) else list(samples or [])
    if info is not None:
        from ago_runtime.formats.mmdet3d_info import load_mmdet3d_info

        info = Path(info)
        frames = load_mmdet3d_info(info, Path(path) if path is not None else info.parent,
                                   allow_outside_root=allow_outside_root)
        if wanted:
            unknown = [w for w in wanted if not any(w in (f.token, f.scene) for f in frames)]
            if unknown:
                raise AgoInputError(info, f"no sample or scene {', '.join(map(repr, unknown))}")
            frames = [f for w in wanted for f in frames if w in (f.token, f.scene)]
        frames = shard_indices(frames, shard)
        frames = [f for f in frames if skip is None or not skip(f.token)]
        return Frames(len(frames), (InputFrame(f.token, f.images, f.rig, str(info)) for f in frames))
    if path is None:
        raise AgoInputError(None, "give --images DIR (or --info PKL)")
    images = Path(path)
    if not images.is_dir():
        raise AgoInputError(images, "images folder not found")
    from ago_runtime.formats.datasets import dataset_layout, open_dataset

    if dataset_layout(images) is not None:   # a nuScenes or Occ3D-Waymo dataset root
        ds = open_dataset(images, load_extras=False, allow_outside_root=allow_outside_root)
        indices = list(ds.indices_of(wanted) if wanted else range(len(ds)))
        indices = shard_indices(indices, shard)   # before resume's skip, so shards never change
        indices = [i for i in indices if skip is None or not skip(ds.sample_tokens[i])]

        def dataset_frames():
            for i in indices:
                f = ds[i]
                yield InputFrame(f.token, f.images, f.rig, str(images))
        return Frames(len(indices), dataset_frames())
    if wanted or shard is not None or allow_outside_root:
        option = "--sample" if wanted else "--shard" if shard is not None else "--allow-outside-root"
        raise AgoInputError(option, f"{images} is an images folder (one frame), not a dataset: the option does not "
                                    "apply to it")
    find_camera_images(images, rig.names if rig is not None else CAMERA_NAMES)   # inside a dataroot: named

    def folder_frame():
        imgs, frame_rig, _ = load_images_folder(images, fallback_rig=rig)
        yield InputFrame(images.resolve().name, imgs, frame_rig, str(images))
    return Frames(1, folder_frame())
