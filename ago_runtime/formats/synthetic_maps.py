"""The per-pixel truth `ago synth` writes beside its images (ours, both layouts; docs/dataset_format.md).

`synthetic/semantic/<CAMERA>/<image stem>.png`: (H, W) uint8 label ids of the dataset's class table
(255 = sky / nothing); `synthetic/depth/<CAMERA>/<image stem>.png`: (H, W) uint16 centimetres (0 = none,
depths clipped to 655.35 m). The nuScenes layout names cameras CAM_FRONT ... and images by their JPEG stem;
the Occ3D-Waymo layout FRONT ... and the sample name (unique across splits: its first digit is the split).
Only the simulated backends of `ago pseudo-labels` read them (`Frame.extras`).

`write_synthetic_maps` writes one camera's maps (temporary file + rename), `read_synthetic_maps` reads
the ones present into a `Frame.extras` dict ({"semantic": {cam: uint8}, "depth": {cam: float32 metres}}),
each checked against its image's size.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ago_runtime.atomic import write_bytes
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.image_files import decode_image

FOLDER = "synthetic"


def read_png(path: str | Path, dtype: type, hw: tuple[int, int] | None = None) -> np.ndarray:
    """A single-channel PNG -> (H, W) array of `dtype` (uint8 or uint16), checked against `hw`."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise AgoInputError(path, f"cannot read the PNG ({e})") from None
    array = decode_image(data, path, cv2.IMREAD_UNCHANGED)
    if array.ndim != 2 or array.dtype != dtype:
        raise AgoInputError(path, f"expected a single-channel {np.dtype(dtype).name} PNG, "
                                  f"got shape {array.shape} {array.dtype}")
    if hw is not None and array.shape != tuple(hw):
        raise AgoInputError(path, f"size {array.shape} does not match its image {tuple(hw)}")
    return array


def map_path(root: str | Path, kind: str, camera: str, stem: str) -> Path:
    """`<root>/synthetic/<kind>/<camera>/<stem>.png` (kind: semantic or depth)."""
    return Path(root) / FOLDER / kind / camera / f"{stem}.png"


def write_png(path: Path, array: np.ndarray) -> None:
    ok, png = cv2.imencode(".png", array)
    if not ok:
        raise AgoInputError(path, "cv2 could not encode the PNG")
    write_bytes(path, png.tobytes())


def write_synthetic_maps(root: str | Path, extras: dict, camera: str, stem: str, hw: tuple[int, int]) -> None:
    """Write `extras["semantic"][camera]` and `extras["depth"][camera]` (each when present), sized `hw`."""
    semantic = (extras.get("semantic") or {}).get(camera)
    if semantic is not None:
        semantic = np.asarray(semantic)
        if semantic.shape != hw:
            raise AgoInputError(root, f"{camera} semantic map must be {hw}, got {semantic.shape}")
        write_png(map_path(root, "semantic", camera, stem), semantic.astype(np.uint8))
    depth = (extras.get("depth") or {}).get(camera)
    if depth is not None:
        depth = np.asarray(depth, dtype=np.float64)
        if depth.shape != hw:
            raise AgoInputError(root, f"{camera} depth map must be {hw}, got {depth.shape}")
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
        centimetres = np.clip(np.round(depth * 100.0), 0, 65535).astype(np.uint16)
        write_png(map_path(root, "depth", camera, stem), centimetres)


def read_synthetic_maps(root: str | Path, extras: dict, camera: str, stem: str, hw: tuple[int, int]) -> None:
    """Add the maps of one camera image that exist under `root` to `extras` (nothing when none do)."""
    semantic = map_path(root, "semantic", camera, stem)
    if semantic.is_file():
        extras.setdefault("semantic", {})[camera] = read_png(semantic, np.uint8, hw)
    depth = map_path(root, "depth", camera, stem)
    if depth.is_file():
        extras.setdefault("depth", {})[camera] = read_png(depth, np.uint16, hw).astype(np.float32) / 100.0
