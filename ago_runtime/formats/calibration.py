"""Calibration files and camera-image folders for `ago infer --images DIR`.

An images folder holds the six surround images named by their nuScenes camera names
(`CAM_FRONT.jpg`, `CAM_FRONT_RIGHT.png`, ... ; .jpg, .jpeg or .png) and, optionally, a
`calib.json` with the rig:

    {
      "format": "ago-calibration",
      "version": 1,
      "cameras": {
        "CAM_FRONT": {"intrinsics": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],   # pixels, 3x3
                      "cam2ego": [[...4 numbers...] x 4],                    # 4x4, metres
                      "width": 1600, "height": 900},                         # image size K refers to
        ... the other five cameras ...
      }
    }

`cameras` may also be a list of objects each with a `"name"` (the layout `Rig.to_dict` writes).
Camera frame: x right, y down, z forward; ego frame: x forward, y left, z up (see camera.py).

Image size rule: when an image's size differs from the size its calibration names, the image is
accepted with a warning (and the intrinsics are scaled to the image) if the aspect ratios agree
within 2 %; otherwise it is refused.

Everything bad (missing/extra camera, unreadable or truncated image, NaN or singular calibration,
mismatched aspect ratio) raises AgoInputError naming the file.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np

from ago_runtime.atomic import write_json
from ago_runtime.geometry.camera import CAMERA_NAMES, Camera, Rig
from ago_runtime.errors import AgoInputError
from ago_runtime.formats.image_files import decode_image
from ago_runtime.readers import read_json

CALIB_FILE = "calib.json"
CALIB_FORMAT = "ago-calibration"
CALIB_VERSION = 1
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
ASPECT_TOLERANCE = 0.02


class AgoInputWarning(UserWarning):
    """A bad-but-usable input (e.g. images resized to match the calibration)."""


def save_calibration(path: str | Path, rig: Rig) -> None:
    """Write `rig` as a calib.json (atomic)."""
    cams = {c.name: {"intrinsics": c.intrinsics.tolist(), "cam2ego": c.cam2ego.tolist(),
                     "width": int(c.width), "height": int(c.height)} for c in rig}
    write_json(path, {"format": CALIB_FORMAT, "version": CALIB_VERSION, "cameras": cams})


def load_calibration(path: str | Path) -> Rig:
    """Read and check a calib.json -> Rig (cameras in CAMERA_NAMES order)."""
    path = Path(path)
    d = read_json(path, missing="calibration file not found")
    if not isinstance(d, dict) or "cameras" not in d:
        raise AgoInputError(path, "calibration needs a 'cameras' entry")
    version = d.get("version", CALIB_VERSION)
    if not isinstance(version, int) or version > CALIB_VERSION:
        raise AgoInputError(path, f"calibration version {version!r} is newer than this ago reads ({CALIB_VERSION})")
    entries = d["cameras"]
    if isinstance(entries, list):
        try:
            entries = {e["name"]: e for e in entries}
        except (TypeError, KeyError):
            raise AgoInputError(path, "each camera in a 'cameras' list needs a 'name'") from None
    if not isinstance(entries, dict):
        raise AgoInputError(path, "'cameras' must be an object keyed by camera name or a list")
    missing = [n for n in CAMERA_NAMES if n not in entries]
    extra = sorted(set(entries) - set(CAMERA_NAMES))
    if missing or extra:
        raise AgoInputError(path, f"calibration needs exactly the six nuScenes cameras; missing {missing}, extra {extra}")
    cams = []
    for name in CAMERA_NAMES:
        e = entries[name]
        try:
            k = np.asarray(e["intrinsics"], dtype=np.float64)
            m = np.asarray(e["cam2ego"], dtype=np.float64)
            w, h = int(e["width"]), int(e["height"])
        except (KeyError, TypeError, ValueError) as ex:
            raise AgoInputError(path, f"{name}: needs intrinsics (3x3), cam2ego (4x4), width, height ({ex})") from None
        if k.shape != (3, 3) or m.shape != (4, 4):
            raise AgoInputError(path, f"{name}: intrinsics must be 3x3 and cam2ego 4x4, got {k.shape} and {m.shape}")
        cams.append(Camera(name, k, m, w, h))
    rig = Rig(cams)
    rig.validate(str(path))
    return rig


def read_image(path: str | Path) -> np.ndarray:
    """An image file -> (H, W, 3) uint8 RGB. Refuses unreadable, truncated, corrupt or oversized files
    (header size limit and corrupt-data check: ago_runtime.formats.image_files)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise AgoInputError(path, f"cannot read image ({e.strerror or e})") from None
    if path.suffix.lower() in (".jpg", ".jpeg"):
        if not data.startswith(b"\xff\xd8"):
            raise AgoInputError(path, "not a JPEG file (no start-of-image marker)")
        if b"\xff\xd9" not in data[-1024:]:
            raise AgoInputError(path, "truncated or corrupt JPEG (no end-of-image marker)")
    img = decode_image(data, path, cv2.IMREAD_COLOR)
    if img.ndim != 3:
        raise AgoInputError(path, "corrupt or unsupported image file")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def find_camera_images(folder: str | Path) -> dict[str, Path]:
    """camera name -> image path in `folder`; refuses a missing, duplicated or unknown CAM_* image."""
    folder = Path(folder)
    if not folder.is_dir():
        raise AgoInputError(folder, "images folder not found")
    found: dict[str, list[Path]] = {}
    unknown = []
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() not in IMAGE_SUFFIXES or not p.is_file():
            continue
        if p.stem in CAMERA_NAMES:
            found.setdefault(p.stem, []).append(p)
        elif p.stem.upper().startswith("CAM_"):
            unknown.append(p.name)
    if unknown:
        raise AgoInputError(folder, f"extra camera image(s) {unknown}; expected only {list(CAMERA_NAMES)}")
    dups = {n: [q.name for q in ps] for n, ps in found.items() if len(ps) > 1}
    if dups:
        raise AgoInputError(folder, f"more than one image for a camera: {dups}")
    missing = [n for n in CAMERA_NAMES if n not in found]
    if missing:
        parent = folder.resolve().parent
        if any(p.is_dir() and p.name.startswith("v1.0") for p in parent.iterdir()):   # e.g. DATAROOT/samples
            raise AgoInputError(folder, f"is inside a nuScenes dataroot: pass the dataroot itself, {parent}")
        raise AgoInputError(folder, f"missing camera image(s) {missing} (expected files like CAM_FRONT.jpg)")
    return {n: found[n][0] for n in CAMERA_NAMES}


def fit_rig_to_images(rig: Rig, images: dict[str, np.ndarray], paths: dict[str, Path] | None = None) -> Rig:
    """Scale each camera to its image's size when the aspect ratio agrees within 2 % (warning), else refuse."""
    cams = []
    for cam in rig:
        h, w = images[cam.name].shape[:2]
        if (w, h) == (cam.width, cam.height):
            cams.append(cam)
            continue
        source = paths[cam.name] if paths else cam.name
        aspect_img, aspect_cal = w / h, cam.width / cam.height
        if abs(aspect_img / aspect_cal - 1.0) > ASPECT_TOLERANCE:
            raise AgoInputError(source, f"image is {w}x{h} but the calibration is for {cam.width}x{cam.height} "
                                        f"(aspect ratios differ by more than {ASPECT_TOLERANCE:.0%})")
        warnings.warn(f"{source}: image is {w}x{h}, calibration is for {cam.width}x{cam.height}; "
                      "scaling the intrinsics to the image", AgoInputWarning, stacklevel=2)
        cams.append(cam.scaled(w, h))
    return Rig(cams)


def load_images_folder(folder: str | Path, fallback_rig: Rig | None = None) -> tuple[dict[str, np.ndarray], Rig, dict[str, Path]]:
    """Read an images folder -> (images RGB uint8 by camera, rig fitted to the images, image paths).

    Without a calib.json, `fallback_rig` (the bundle's training rig) is used with a warning.
    """
    folder = Path(folder)
    paths = find_camera_images(folder)
    calib = folder / CALIB_FILE
    if calib.is_file():
        rig = load_calibration(calib)
    elif fallback_rig is not None:
        warnings.warn(f"{folder}: no {CALIB_FILE}; using the bundle's training rig (predictions will be wrong "
                      "if your cameras sit elsewhere)", AgoInputWarning, stacklevel=2)
        rig = fallback_rig
    else:
        raise AgoInputError(calib, "calibration file not found")
    images = {name: read_image(p) for name, p in paths.items()}
    return images, fit_rig_to_images(rig, images, paths), paths
