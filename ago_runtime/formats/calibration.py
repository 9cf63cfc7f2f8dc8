"""Calibration files and camera-image folders for `ago infer --images DIR`.

An images folder holds one image per camera of the rig, named by the camera (`CAM_FRONT.jpg`,
`CAM_FRONT_RIGHT.png`, ... for nuScenes' six; `FRONT.jpg` ... for a rig of other names; .jpg, .jpeg
or .png) and, optionally, a `calib.json` with the rig:

    {
      "format": "ago-calibration",
      "version": 1,
      "cameras": {
        "CAM_FRONT": {"intrinsics": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],   # pixels, 3x3
                      "cam2ego": [[...4 numbers...] x 4],                    # 4x4, metres
                      "width": 1600, "height": 900},                         # image size K refers to
        ... the other cameras ...
      }
    }

Which cameras: the bundle's rig names them (its order is the model's input order); a calib.json
with a camera the bundle's rig lacks, or without one it takes, is refused naming the camera. A
calib.json read on its own gives its cameras in the file's order.

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
from ago_runtime.geometry.camera import CAMERA_NAMES, MAX_CAMERAS, Camera, Rig
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


def load_calibration(path: str | Path, names=None) -> Rig:
    """Read and check a calib.json -> Rig: its cameras in `names`' order (a bundle's rig: a missing or an
    extra camera is refused, naming it), or in the file's order without `names`."""
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
    if not 1 <= len(entries) <= MAX_CAMERAS:
        raise AgoInputError(path, f"calibration needs 1..{MAX_CAMERAS} cameras, got {len(entries)}")
    cams = []
    for name, e in entries.items():
        if not isinstance(e, dict):
            raise AgoInputError(path, f"{name}: a camera entry must be an object")
        try:
            k = np.asarray(e["intrinsics"], dtype=np.float64)
            m = np.asarray(e["cam2ego"], dtype=np.float64)
            w, h = int(e["width"]), int(e["height"])
        except (KeyError, TypeError, ValueError) as ex:
            raise AgoInputError(path, f"{name}: needs intrinsics (3x3), cam2ego (4x4), width, height ({ex})") from None
        if k.shape != (3, 3) or m.shape != (4, 4):
            raise AgoInputError(path, f"{name}: intrinsics must be 3x3 and cam2ego 4x4, got {k.shape} and {m.shape}")
        cams.append(Camera(name, k, m, w, h))
    try:
        rig = Rig(cams)
        rig = rig.ordered_as(names) if names is not None else rig
    except AgoInputError as e:
        raise AgoInputError(path, e.problem) from None
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


def find_camera_images(folder: str | Path, names=CAMERA_NAMES) -> dict[str, Path]:
    """camera name -> image path in `folder` for the cameras `names` (default nuScenes' six); refuses a
    missing or duplicated camera image, and a CAM_* image or an image named like a camera of `names`
    in another case that is not one of them."""
    folder = Path(folder)
    names = list(names)
    if not folder.is_dir():
        raise AgoInputError(folder, "images folder not found")
    found: dict[str, list[Path]] = {}
    unknown = []
    upper = {n.upper() for n in names}
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() not in IMAGE_SUFFIXES or not p.is_file():
            continue
        if p.stem in names:
            found.setdefault(p.stem, []).append(p)
        elif p.stem.upper().startswith("CAM_") or p.stem.upper() in upper:
            unknown.append(p.name)
    if unknown:
        raise AgoInputError(folder, f"extra camera image(s) {unknown}; expected only {names}")
    dups = {n: [q.name for q in ps] for n, ps in found.items() if len(ps) > 1}
    if dups:
        raise AgoInputError(folder, f"more than one image for a camera: {dups}")
    missing = [n for n in names if n not in found]
    if missing:
        parent = folder.resolve().parent
        if any(p.is_dir() and p.name.startswith("v1.0") for p in parent.iterdir()):   # e.g. DATAROOT/samples
            raise AgoInputError(folder, f"is inside a nuScenes dataroot: pass the dataroot itself, {parent}")
        raise AgoInputError(folder, f"missing camera image(s) {missing} (expected files like {names[0]}.jpg)")
    return {n: found[n][0] for n in names}


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


def load_images_folder(folder: str | Path, fallback_rig: Rig | None = None,
                       names=None) -> tuple[dict[str, np.ndarray], Rig, dict[str, Path]]:
    """Read an images folder -> (images RGB uint8 by camera, rig fitted to the images, image paths).

    The cameras: `names` (the bundle's rig), else `fallback_rig`'s, else the calib.json's. Without a
    calib.json, `fallback_rig` (the bundle's training rig) is used with a warning.
    """
    folder = Path(folder)
    calib = folder / CALIB_FILE
    if names is None and fallback_rig is not None:
        names = fallback_rig.names
    if calib.is_file():
        rig = load_calibration(calib, names)
    elif fallback_rig is not None:
        if not folder.is_dir():
            raise AgoInputError(folder, "images folder not found")
        warnings.warn(f"{folder}: no {CALIB_FILE}; using the bundle's training rig (predictions will be wrong "
                      "if your cameras sit elsewhere)", AgoInputWarning, stacklevel=2)
        rig = fallback_rig.ordered_as(names) if names is not None else fallback_rig
    else:
        if not folder.is_dir():
            raise AgoInputError(folder, "images folder not found")
        raise AgoInputError(calib, "calibration file not found")
    paths = find_camera_images(folder, rig.names)
    images = {name: read_image(p) for name, p in paths.items()}
    return images, fit_rig_to_images(rig, images, paths), paths
